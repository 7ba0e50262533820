"""constrained.sweeps.sweep: specs, the Kapitza stability map, Dask vs sequential, resume, bad input."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from interrupting import env as _env

import constrained as C
from constrained.cli.main import main
from constrained.errors import InputError
from constrained.sweeps import sweep as S

ROOT = Path(__file__).resolve().parents[1]
KAPITZA = ROOT / "scenarios" / "kapitza_sweep.toml"
UP = "min:up=y_bob - a*cos(nu*t)"  # smallest height of the bob above the pivot: > 0 stayed inverted
GRID = ["parameters.a=lin(0.002, 0.02, 12)", "parameters.nu=lin(20, 240, 12)"]
G, L = 9.81, 0.1

distributed = pytest.importorskip("distributed")




def _compare(rows_a, rows_b, tol=1e-12, skip=("run", "run_id", "status")):
    """Same run ids, same status, numbers equal to ``tol`` (relative to max(1, |value|)), the
    other columns (method, path) equal."""
    by_id = {r["run_id"]: r for r in rows_b}
    assert {r["run_id"] for r in rows_a} <= set(by_id)
    for ra in rows_a:
        rb = by_id[ra["run_id"]]
        assert ra["status"] == rb["status"] == "ok"
        for k, va in ra.items():
            if k in skip:
                continue
            vb = rb[k]
            if isinstance(va, str) or va is None:
                assert va == vb, (k, va, vb)
                continue
            assert abs(float(va) - float(vb)) <= tol * max(1.0, abs(float(va))), (k, va, vb)


def _chunk_rows(out) -> list[dict]:
    """Every row of the chunk files in ``out/chunks`` (with the chunk's metadata as "meta")."""
    import pyarrow.parquet as pq

    rows = []
    for path in sorted((Path(out) / "chunks").glob("*.parquet")):
        table = pq.read_table(path)
        meta = json.loads(table.schema.metadata[b"constrained"])
        rows += [{**r, "meta": meta} for r in table.to_pylist()]
    return rows


# --- specs and design ------------------------------------------------------------------------


def test_specs_and_design():
    assert S.parse_vary("parameters.k=lin(1, 3, 3)").values == (1.0, 2.0, 3.0)
    assert np.allclose(S.parse_vary("parameters.k=log(1, 100, 3)").values, [1, 10, 100])
    assert S.parse_vary("particles.p1.mass=[1, 2.5]").values == (1, 2.5)
    assert S.parse_vary("particles[0].position=[[1, 0, 0], [2, 0, 0]]").values == ([1, 0, 0], [2, 0, 0])
    spec = S.parse_vary("particles.p2.position[0]=normal(1.5, 1e-9)")
    assert spec.random and spec.name == "position"
    grid = S.design([S.parse_vary("parameters.a=[1, 2]"), S.parse_vary("parameters.b=[3, 4, 5]")])
    assert [tuple(p.values()) for p in grid] == [(1, 3), (1, 4), (1, 5), (2, 3), (2, 4), (2, 5)]
    rnd = [S.parse_vary("parameters.a=uniform(0, 1)"), S.parse_vary("parameters.b=loguniform(1, 10)")]
    d1, d2 = S.design(rnd, samples=5, seed=3), S.design(rnd, samples=5, seed=3)
    assert d1 == d2 and len(d1) == 5 and d1 != S.design(rnd, samples=5, seed=4)
    assert all(0 <= p["parameters.a"] <= 1 and 1 <= p["parameters.b"] <= 10 for p in d1)
    assert S.run_id({"parameters.a": 0.1}) == S.run_id({"parameters.a": 0.1})
    assert S.run_id({"parameters.a": 0.1}) != S.run_id({"parameters.a": 0.1 + 1e-16})
    for bad, words in [("parameters.a=lin(1, 2)", "takes 3 numbers"), ("parameters.a=foo(1)", "unknown spec"),
                       ("parameters.a=uniform(2, 1)", "low < high"), ("parameters.a=[1, 2", "cannot read"),
                       ("parameters.a=lin(1, 2, x)", "not a number"), ("parameters a=[1]", "not a key path"),
                       ("parameters.a", "KEY=SPEC")]:
        with pytest.raises(InputError, match=words):
            S.parse_vary(bad)
    with pytest.raises(InputError, match="needs --samples"):
        S.design(rnd)
    for bad in ("theta", "median:x=1", "2x=1"):
        with pytest.raises(InputError):
            S.parse_summary(bad)
    assert S.parse_summary("max_abs:th=atan2(x_bob, -y_bob)").reduction == "max_abs"


def test_toml_values_read_back_exactly():
    import tomllib

    for v in (0.1, 1e-300, 2.0, 3, -1.5e20, [1, 2.5, 0.0], "sin(t)", True):
        assert tomllib.loads(f"v = {S.toml_value(v)}")["v"] == v


# --- the Kapitza stability map on the default local cluster ----------------------------------


@pytest.fixture(scope="module")
def kapitza(tmp_path_factory):
    """The 12 x 12 (a, nu) sweep on a local Dask cluster (one process per core)."""
    out = tmp_path_factory.mktemp("kapitza")
    started = time.perf_counter()
    result = S.sweep(KAPITZA, GRID, summary=[UP], out_dir=out, progress=False, boundary="a**2*nu**2 - 2*g*l",
                     scheduler="local")
    result.elapsed = time.perf_counter() - started
    return result


def test_kapitza_map_agrees_with_the_analytic_threshold(kapitza):
    r = kapitza
    assert r.total == 144 and r.computed == 144 and r.failed == 0 and r.complete
    a_values, nu_values = r.specs[0].values, r.specs[1].values
    ea, en = S.cell_edges(a_values), S.cell_edges(nu_values)
    up = r.column("up").reshape(12, 12)  # first key (a) slowest
    crossed = disagree = 0
    for i, a in enumerate(a_values):
        for j, nu in enumerate(nu_values):
            corners = [aa**2 * nn**2 - 2 * G * L for aa in ea[i:i + 2] for nn in en[j:j + 2]]
            if min(corners) < 0 < max(corners):
                crossed += 1
                continue
            stable = a**2 * nu**2 > 2 * G * L
            disagree += (up[i, j] > 0) != stable
    assert disagree == 0
    assert 5 < crossed < 40  # the boundary runs across the map
    assert (up > 0).sum() > 30 and (up < 0).sum() > 30
    assert (r.out_dir / "sweep.png").stat().st_size > 10_000
    assert (r.out_dir / "summary.csv").is_file()
    assert r.workers == (os.cpu_count() or 1)
    # rows in design order, the varied values as columns, status ok, residuals tiny
    assert [row["run"] for row in r.rows] == list(range(144))
    assert r.rows[13]["parameters.a"] == a_values[1] and r.rows[13]["parameters.nu"] == nu_values[1]
    assert np.all(r.column("max_constraint_residual") < 1e-10)


def test_parquet_and_csv_tables(kapitza):
    import csv

    rows = list(csv.DictReader(open(kapitza.out_dir / "summary.csv")))
    assert len(rows) == 144
    def cell(k, v):
        if k in ("run_id", "status", "method", "path"):
            return v
        return None if v == "" else float(v)

    _compare(kapitza.rows, [{k: cell(k, v) for k, v in r.items()} for r in rows])
    assert {r["method"] for r in rows} == {"rattle"} and {r["path"] for r in rows} == {"per-run"}
    pq = pytest.importorskip("pyarrow.parquet")
    table = pq.read_table(kapitza.out_dir / "summary.parquet").to_pylist()
    _compare(kapitza.rows, table)


# --- the same table sequentially, locally and on a real Dask cluster ---------------------------


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def dask_cluster(tmp_path_factory):
    """A `dask scheduler` and two `dask worker` processes on 127.0.0.1; killed afterwards."""
    tmp = tmp_path_factory.mktemp("dask")
    dask = str(Path(sys.executable).with_name("dask"))
    if not Path(dask).exists():
        pytest.skip("the dask command is not installed")
    address = f"tcp://127.0.0.1:{_free_port()}"
    procs = []
    logs = []

    def start(args, name):
        log = open(tmp / f"{name}.log", "wb")
        logs.append(log)
        procs.append(subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT, env=_env(), cwd=tmp,
                                      start_new_session=True))

    try:
        local = ["--no-dashboard", "--dashboard-address", "127.0.0.1:0"]  # its HTTP server on loopback too
        start([dask, "scheduler", "--host", "127.0.0.1", "--port", address.rsplit(":", 1)[1], *local],
              "scheduler")
        for k in range(2):
            start([dask, "worker", address, "--host", "127.0.0.1", "--nthreads", "1", "--nworkers", "1",
                   *local, "--name", f"w{k}"], f"worker{k}")
        deadline = time.monotonic() + 60
        client = None
        while client is None:
            try:
                client = distributed.Client(address, timeout=5)
            except OSError:
                if time.monotonic() > deadline or any(p.poll() is not None for p in procs):
                    raise
                time.sleep(0.5)
        client.wait_for_workers(2, timeout=60)
        client.close()
        yield address
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in reversed(procs):
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(timeout=10)
        for log in logs:
            log.close()


_NU = S.parse_vary(GRID[1]).values
SMALL = [GRID[0], f"parameters.nu=[{_NU[3]!r}, {_NU[9]!r}]"]  # 24 runs, the same as in the 12 x 12 grid


def test_same_table_sequential_local_and_remote(kapitza, dask_cluster, tmp_path):
    seq = S.sweep(KAPITZA, SMALL, summary=[UP], out_dir=tmp_path / "seq", scheduler="sequential",
                  progress=False)
    remote = S.sweep(KAPITZA, SMALL, summary=[UP], out_dir=tmp_path / "remote", scheduler=dask_cluster,
                     progress=False)
    assert seq.computed == remote.computed == 24 and remote.workers == 2
    assert seq.columns == remote.columns
    _compare(seq.rows, remote.rows)
    _compare(seq.rows, kapitza.rows)  # the same runs inside the 12 x 12 sweep (local cluster)
    workers = {r["meta"]["worker"] for r in _chunk_rows(tmp_path / "remote")}
    assert len(workers) == 2  # both dask workers took chunks


def test_a_batched_sweep_on_a_running_scheduler_gives_the_in_process_numbers(dask_cluster, tmp_path):
    """The cluster contract for the batched path: chunks of simulate_many on two `dask worker`
    processes give the numbers of the same sweep in this process, bit for bit."""
    scene = tmp_path / "double.toml"
    text = (ROOT / "scenarios" / "double_pendulum_parametric.toml").read_text().split("[expect]")[0]
    scene.write_text(text.replace('method = "projection"', 'method = "dopri"'))
    vary = ["parameters.m1=uniform(0.5, 2)", "parameters.th2=uniform(1.5, 2.5)"]
    kw = dict(samples=16, summary=["max_abs:w=vx_p2"], overrides=["simulate.t_end=1.0"], progress=False,
              chunk_size=4, figure=False)
    here = S.sweep(scene, vary, out_dir=tmp_path / "here", scheduler="sequential", **kw)
    there = S.sweep(scene, vary, out_dir=tmp_path / "there", scheduler=dask_cluster, **kw)
    assert here.batched == there.batched == 16 and there.where.mode == "cluster" and there.workers == 2
    assert here.columns == there.columns
    _compare(here.rows, there.rows, tol=0.0)
    assert len({r["meta"]["worker"] for r in _chunk_rows(tmp_path / "there")}) == 2  # 4 chunks, 2 workers


def test_cli_on_a_running_scheduler(dask_cluster, tmp_path, capsys):
    out = tmp_path / "cli"
    code = main(["sweep", str(KAPITZA), "--vary", "parameters.nu=[60, 200]", "--scheduler", dask_cluster,
                 "--summary", UP, "--out", str(out), "--quiet"])
    assert code == 0
    assert len((out / "summary.csv").read_text().splitlines()) == 3
    assert (out / "sweep.png").is_file()  # 1-D: up against nu


# --- interrupted sweeps ----------------------------------------------------------------------


def test_a_killed_sweep_run_again_computes_only_the_missing_runs(kapitza, tmp_path):
    out = tmp_path / "killed"
    args = [sys.executable, "-m", "constrained.cli", "sweep", str(KAPITZA), "--vary", SMALL[0],
            "--vary", SMALL[1], "--summary", UP, "--out", str(out), "--scheduler", "sequential", "--quiet"]
    proc = subprocess.Popen(args, env=_env(), cwd=tmp_path, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    chunks = out / "chunks"
    try:
        deadline = time.monotonic() + 60
        while not list(chunks.glob("*.parquet")):
            assert proc.poll() is None, "the sweep finished before it could be killed"
            assert time.monotonic() < deadline
            time.sleep(0.02)
        proc.kill()
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=10)
    done = len(_chunk_rows(out))
    assert 1 <= done < 24
    assert not list(chunks.glob(".*.part"))  # atomic writes: nothing half-written counts as done
    again = S.sweep(KAPITZA, SMALL, summary=[UP], out_dir=out, scheduler="sequential", progress=False)
    assert again.skipped == done and again.computed == 24 - done and again.complete
    _compare(again.rows, kapitza.rows)  # nothing lost, nothing different
    third = S.sweep(KAPITZA, SMALL, summary=[UP], out_dir=out, scheduler="sequential", progress=False)
    assert third.computed == 0 and third.skipped == 24


def test_limit_and_a_different_sweep_in_the_same_directory(tmp_path):
    vary = ["parameters.nu=lin(50, 200, 6)"]
    first = S.sweep(KAPITZA, vary, summary=[UP], out_dir=tmp_path, scheduler="sequential", progress=False,
                    limit=2)
    assert first.computed == 2 and not first.complete and len(first.rows) == 2
    rest = S.sweep(KAPITZA, vary, summary=[UP], out_dir=tmp_path, scheduler="sequential", progress=False)
    assert rest.skipped == 2 and rest.computed == 4 and rest.complete
    with pytest.raises(InputError, match="different sweep"):
        S.sweep(KAPITZA, vary, summary=["final:h=y_bob"], out_dir=tmp_path, scheduler="sequential",
                progress=False)


# --- failures and bad input ------------------------------------------------------------------


def test_a_failing_run_is_recorded_and_the_others_finish(tmp_path):
    r = S.sweep(KAPITZA, ["particles.bob.mass=[0.1, -1.0, 0.2]"], out_dir=tmp_path, scheduler="sequential",
                progress=False, overrides=["simulate.t_end=0.1"])
    assert [row["status"] == "ok" for row in r.rows] == [True, False, True]
    assert "mass" in r.rows[1]["status"] and "positive" in r.rows[1]["status"]
    assert r.failed == 1 and r.complete
    assert np.isnan(r.column("x_bob")[1]) and np.isfinite(r.column("x_bob")[[0, 2]]).all()
    rec = {row["run_id"]: row for row in _chunk_rows(tmp_path)}[r.rows[1]["run_id"]]
    assert rec["status"] == r.rows[1]["status"]


@pytest.mark.parametrize("vary, words", [
    ("parameters.zz=[1, 2]", "no parameter 'zz'"),
    ("particles.nobody.mass=[1, 2]", "nobody"),
    ("particles.bob.colour=[1, 2]", "colour"),
    ("parameters.a=lin(1, 2)", "takes 3 numbers"),
    ("parameters.a=gauss(1, 2)", "unknown spec function 'gauss'"),
    ("parameters.a=uniform(0, 1)", "needs --samples"),
    ("simulate.method=[\"nonsense\"]", "unknown method"),
])
def test_bad_vary_exits_2_with_a_clear_message(vary, words, tmp_path, capsys):
    out = tmp_path / "bad"
    code = main(["sweep", str(KAPITZA), "--vary", vary, "--out", str(out), "--scheduler", "sequential"])
    err = capsys.readouterr().err
    assert code == 2
    assert words in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert not out.exists()  # nothing written


def test_bad_summary_or_scheduler_exits_2(tmp_path, capsys):
    base = ["sweep", str(KAPITZA), "--vary", "parameters.nu=[60]", "--out", str(tmp_path / "o")]
    assert main([*base, "--summary", "h=y_nobody", "--scheduler", "sequential"]) == 2
    assert "y_nobody" in capsys.readouterr().err
    assert main([*base, "--scheduler", "localhost:1"]) == 2
    assert "tcp://" in capsys.readouterr().err


# --- what a worker caches --------------------------------------------------------------------


def test_runs_that_change_only_the_start_share_one_model(tmp_path):
    S._MODEL_CACHE.clear()
    before = dict(S.CACHE_STATS)
    r = S.sweep(KAPITZA, ["particles.bob.velocity=[[0, 0, 0], [0.01, 0, 0], [0.02, 0, 0]]",
                          "simulate.t_end=[0.05, 0.1]"],
                out_dir=tmp_path, scheduler="sequential", progress=False, save_trajectories=True,
                summary=["max_abs:vx=vx_bob", "mean:h=y_bob"])
    assert r.computed == 6 and r.failed == 0
    assert S.CACHE_STATS["assembled"] - before["assembled"] == 1
    assert S.CACHE_STATS["reused"] - before["reused"] == 5
    assert r.column("t_final").tolist() == [0.05, 0.1] * 3
    assert len(list((tmp_path / "runs").glob("*.npz"))) == 6
    p = S.sweep(KAPITZA, ["parameters.nu=[100, 150]"], out_dir=tmp_path / "p", scheduler="sequential",
                progress=False, overrides=["simulate.t_end=0.05"], summary=["final:nu_seen=2*nu"])
    assert p.column("nu_seen").tolist() == [200.0, 300.0]  # each run's own value, not the cached one
    ref = C.load_scene(KAPITZA, ["parameters.nu=150", "simulate.t_end=0.05"]).run(quantities=[]).trajectory
    assert p.column("y_bob")[1] == pytest.approx(ref.x[-1, 0, 1], abs=1e-12)  # as if rebuilt
    # the parameters are inputs of the model's Functions: new values reuse the structure
    assert p.computed == 2 and S.CACHE_STATS["assembled"] - before["assembled"] == 1
    assert S.CACHE_STATS["reused"] - before["reused"] == 7


def test_boundary_function_is_parsed_not_evaluated():
    f = S.boundary_function("a**2*nu**2 - 2*g*l", ["a", "nu"], {"g": 9.81, "l": 0.1, "a": 5.0})
    assert np.allclose(f(np.array([0.01, 0.02]), np.array([100.0, 100.0])), [1 - 1.962, 4 - 1.962])
    with pytest.raises(InputError):
        S.boundary_function("__import__('os')", ["a"], {})


def test_expect_checks_become_columns(tmp_path):
    path = ROOT / "scenarios" / "atwood_machine.toml"
    r = S.sweep(path, ["simulate.rtol=[1e-9]"], out_dir=tmp_path, scheduler="sequential", progress=False,
                figure=False)
    assert r.rows[0]["status"] == "ok"
    checks = [c for c in r.columns if c.startswith("expect.") and not c.endswith(".ok")]
    assert checks and all(f"{c}.ok" in r.columns for c in checks)


def test_sweep_runs_compile_nothing_unless_the_scene_asks(tmp_path):
    from constrained.scene.load import load_scene
    from constrained.sweeps.sweep import _settings_kwargs

    scene = load_scene(ROOT / "scenarios" / "double_pendulum.toml", ["simulate.method=dopri"])
    assert _settings_kwargs(scene, set())["compiled"] is False  # "auto": a compile per variant
    scene = load_scene(ROOT / "scenarios" / "double_pendulum.toml",
                       ["simulate.method=dopri", "simulate.compiled=true"])
    assert _settings_kwargs(scene, set())["compiled"] is True


def test_a_sweep_runs_method_reduced_through_the_one_map_of_settings(tmp_path):
    """Every run of ``--set simulate.method=reduced`` used to fail ("needs generalized
    coordinates"): sweeps now build their runs in run_options like ``run`` does. The reduced
    route's small-angle motion follows gravity: θ(t) ≈ θ0 cos(√(g/l) t)."""
    import csv

    scene = ROOT / "scenarios" / "simple_pendulum.toml"
    out = tmp_path / "reduced"
    code = main(["sweep", str(scene), "--vary", "parameters.g=[4.0, 16.0]", "--set",
                 "simulate.method=reduced", "--set", "simulate.t_end=1.0", "--out", str(out),
                 "--scheduler", "sequential", "--quiet"])
    assert code == 0
    rows = list(csv.DictReader(open(out / "summary.csv")))
    assert [r["status"] for r in rows] == ["ok", "ok"]
    for row in rows:
        g = float(row["parameters.g"])
        # 0.2 rad from rest, l = 1 m: at t = 1 s, θ = 0.2 cos(√g t) to O(θ³) (frequency shift θ0²/16)
        th = 0.2 * np.cos(np.sqrt(g) * (1 - 0.2**2 / 16) * 1.0)
        assert float(row["x_bob"]) == pytest.approx(np.sin(th), abs=2e-3)


# --- the default figure and folder (issue 32) ---------------------------------------------------


def test_default_folder_does_not_double_the_word():
    assert S.default_out_dir(Path("scenarios/kapitza_sweep.toml")) == Path("out/kapitza_sweep")
    assert S.default_out_dir(Path("double_pendulum.toml")) == Path("out/double_pendulum_sweep")
    assert S.default_out_dir(Path("sweep.toml")) == Path("out/sweep_sweep")  # nothing else to name it by


def test_default_figure_of_a_driven_scene_is_a_coordinate_in_metres(tmp_path, monkeypatch):
    """The Kapitza pendulum is driven (its pivot moves): its energy drift says nothing about the
    scene. Without --plot or --summary the figure shows the position coordinate that the varied
    drive changes most across the runs, labelled in metres; with --summary, the summary."""
    from constrained.sweeps.plot import axis_label, default_column

    monkeypatch.chdir(tmp_path)
    r = S.sweep(KAPITZA, ["parameters.nu=[40, 140, 240]"], overrides=["simulate.t_end=0.6"], progress=False)
    assert r.out_dir == Path("out/kapitza_sweep") and (r.out_dir / "sweep.png").is_file()
    column, why = default_column(r)
    assert column != "energy_drift" and np.ptp(r.column("energy_drift")) > 0  # (it does vary)
    positions = [c for c in r.columns if re.fullmatch(r"(?:(?:min|max)_)?[xyz]_bob", c)]
    assert column in positions
    assert np.ptp(r.column(column)) == max(np.ptp(r.column(c)) for c in positions)
    assert axis_label(column).endswith("[m]") and "bob" in axis_label(column) and "--plot" in why
    # the slow drive lets the bob fall, the fast one holds it up: the lowest height differs by ~l
    assert np.ptp(r.column("min_y_bob")) > 0.1
    r2 = S.sweep(KAPITZA, ["parameters.nu=[40, 240]"], overrides=["simulate.t_end=0.6"], summary=[UP],
                 out_dir=tmp_path / "with_summary", progress=False)
    assert default_column(r2, ["up"]) == ("up", "")
