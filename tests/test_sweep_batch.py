"""Sweeps in chunks (issue 17, items 2-3): variants that differ only in [parameters] run
batched (simulate_many per chunk) and give the per-run path's numbers; chunk files resume
per variant, unreadable ones are computed again; --design files; Ctrl-C keeps finished
chunks; in-process vs Dask chosen by the estimated work."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from interrupting import interrupt_when

from constrained.cli.main import main
from constrained.sweeps import execute as sweep_execute
from constrained.sweeps import sweep as S

ROOT = Path(__file__).resolve().parents[1]
PARAMETRIC = ROOT / "scenarios" / "double_pendulum_parametric.toml"
pq = pytest.importorskip("pyarrow.parquet")
pa = pytest.importorskip("pyarrow")




@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """The parametric double pendulum, method dopri, without [expect] (which needs a run's
    Trajectory), outputs every 0.1 s to t = 2 s."""
    text = PARAMETRIC.read_text().split("[expect]")[0]
    text = text.replace('method = "projection"', 'method = "dopri"').replace("t_end = 10.0", "t_end = 2.0")
    text = text.replace("atol = 1e-12", "atol = 1e-12\noutput_dt = 0.1")
    path = tmp_path_factory.mktemp("scene") / "double.toml"
    path.write_text(text)
    return path


RANDOM = ["parameters.m1=uniform(0.5, 2)", "parameters.l2=uniform(0.6, 1.4)",
          "parameters.th1=uniform(1.0, 2.5)"]
SUMMARY = ["max:top=y_p2", "mean:kin=0.5*m2*(vx_p2**2 + vy_p2**2)"]


def _compare(rows_a, rows_b, tol, skip=("path",)):
    assert [r["run_id"] for r in rows_a] == [r["run_id"] for r in rows_b]
    for ra, rb in zip(rows_a, rows_b, strict=True):
        assert ra.keys() == rb.keys()
        for k, va in ra.items():
            if k in skip:
                continue
            if isinstance(va, float):
                assert abs(va - rb[k]) <= tol * max(1.0, abs(va)), (k, va, rb[k])
            else:
                assert va == rb[k], (k, va, rb[k])


def _chunk_files(out) -> list[Path]:
    return sorted((Path(out) / "chunks").glob("*.parquet"))


@pytest.fixture(scope="module")
def batched(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("batched")
    return S.sweep(scene, RANDOM, samples=12, seed=5, summary=SUMMARY, out_dir=out, progress=False,
                   chunk_size=5, figure=False)


def test_batched_rows_equal_the_per_run_path_and_the_rods_keep_their_lengths(scene, batched, tmp_path):
    per_run = S.sweep(scene, RANDOM, samples=12, seed=5, summary=SUMMARY, out_dir=tmp_path, progress=False,
                      batch=False, scheduler="sequential", figure=False)
    assert batched.batched == 12 and batched.per_run == 0 and per_run.per_run == 12
    assert {r["path"] for r in batched.rows} == {"batched"}
    assert {r["path"] for r in per_run.rows} == {"per-run"}
    assert batched.columns == per_run.columns
    # the same output times and steps: the same numbers, to round-off
    _compare(batched.rows, per_run.rows, 1e-9)
    for r in batched.rows:
        assert r["status"] == "ok" and r["method"] == "dopri(DOP853)"
        assert r["rtol"] == 1e-10 and r["dt"] is None
        l2 = r["parameters.l2"]
        assert np.hypot(r["x_p1"], r["y_p1"]) == pytest.approx(1.0, abs=1e-9)  # l1 = 1
        assert np.hypot(r["x_p2"] - r["x_p1"], r["y_p2"] - r["y_p1"]) == pytest.approx(l2, abs=1e-9)
        assert r["energy_drift"] < 1e-7 and r["max_constraint_residual"] < 1e-9
        assert r["max_y_p2"] == r["top"]  # max:top=y_p2 over the same samples
    # three chunk files of 5, 5 and 2 variants
    assert sorted(pq.read_table(p).num_rows for p in _chunk_files(batched.out_dir)) == [2, 5, 5]


def test_resume_is_per_variant_and_an_unreadable_chunk_is_computed_again(scene, batched, tmp_path):
    import shutil

    out = tmp_path / "resume"
    shutil.copytree(batched.out_dir, out)
    files = _chunk_files(out)
    gone = {r["run_id"] for r in pq.read_table(files[0]).to_pylist()}
    files[0].unlink()  # a chunk lost
    broken = {r["run_id"] for r in pq.read_table(files[1]).to_pylist()}
    data = files[1].read_bytes()
    files[1].write_bytes(data[: len(data) // 2])  # a chunk cut short (not by our atomic writes)
    again = S.sweep(scene, RANDOM, samples=12, seed=5, summary=SUMMARY, out_dir=out, progress=False,
                    chunk_size=5, figure=False)
    assert again.computed == len(gone | broken) and again.skipped == 12 - len(gone | broken)
    assert len(again.warnings) == 1 and str(files[1]) in again.warnings[0]
    _compare(again.rows, batched.rows, 0.0)  # nothing lost, nothing different
    third = S.sweep(scene, RANDOM, samples=12, seed=5, summary=SUMMARY, out_dir=out, progress=False,
                    figure=False)
    assert third.computed == 0 and third.skipped == 12 and not third.warnings


def _write_design(path: Path, columns: dict) -> Path:
    if path.suffix == ".csv":
        with open(path, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(columns)
            w.writerows(zip(*columns.values(), strict=True))
    else:
        pq.write_table(pa.table(columns), path)
    return path


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_a_design_file_runs_its_rows_as_a_vary_grid_would(scene, tmp_path, suffix):
    m1, l2 = [0.8, 0.8, 1.3, 1.3], [0.9, 1.1, 0.9, 1.1]
    path = _write_design(tmp_path / f"design{suffix}", {"parameters.m1": m1, "parameters.l2": l2})
    r = S.sweep(scene, design_file=path, out_dir=tmp_path / "d", progress=False, figure=False)
    grid = S.sweep(scene, ["parameters.m1=[0.8, 1.3]", "parameters.l2=[0.9, 1.1]"], out_dir=tmp_path / "g",
                   progress=False, figure=False)
    assert [row["parameters.m1"] for row in r.rows] == m1 and [row["parameters.l2"] for row in r.rows] == l2
    _compare(r.rows, grid.rows, 0.0)  # the same variants (the same run ids), the same numbers
    # crossed with a --vary grid: the file's rows slowest
    crossed = S.sweep(scene, ["parameters.th1=[1.5, 2.0]"], design_file=path, out_dir=tmp_path / "c",
                      progress=False, figure=False)
    assert crossed.total == 8 and [row["parameters.th1"] for row in crossed.rows[:2]] == [1.5, 2.0]


@pytest.mark.parametrize("content, words", [
    ("", "the file is empty"),
    ("parameters.m1\n", "no rows"),
    ("parameters.m1,parameters.zz\n1.0,2.0\n", "column 'parameters.zz': the scene has no parameter 'zz'"),
    ("parameters.m1\n1.0\nabc\n", "line 3, column 'parameters.m1': 'abc' is not a number"),
    ("parameters.m1\n1.0\nnan\n", "line 3, column 'parameters.m1': 'nan' is not a finite number"),
    ("parameters.m1,parameters.l2\n1.0\n", "line 2 has 1 values for 2 columns"),
    ("parameters m1\n1.0\n", "'parameters m1' is not a scene key"),
    ("parameters.m1,parameters.m1\n1.0,2.0\n", "appears twice"),
])
def test_a_bad_design_file_exits_2_naming_the_file_and_what_is_wrong(scene, tmp_path, capsys, content, words):
    path = tmp_path / "bad.csv"
    path.write_text(content)
    out = tmp_path / "out"
    code = main(["sweep", str(scene), "--design", str(path), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert words in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert str(path) in err
    assert not out.exists()


def test_bad_parquet_designs_and_file_types_exit_2(scene, tmp_path, capsys):
    cases = [(_write_design(tmp_path / "text.parquet", {"parameters.m1": ["heavy"]}),
              "row 1, column 'parameters.m1': 'heavy' is not a number"),
             (_write_design(tmp_path / "none.parquet", {"parameters.m1": [1.0, None]}),
              "row 2, column 'parameters.m1': None is not a number"),
             (tmp_path / "junk.parquet", "not a readable Parquet file"),
             (tmp_path / "d.xlsx", "give a .csv or .parquet file"),
             (tmp_path / "missing.csv", "no such file")]
    (tmp_path / "junk.parquet").write_bytes(b"not parquet at all")
    (tmp_path / "d.xlsx").write_bytes(b"")
    for path, words in cases:
        code = main(["sweep", str(scene), "--design", str(path), "--out", str(tmp_path / "o"), "--quiet"])
        err = capsys.readouterr().err
        assert code == 2 and words in err and str(path) in err and "Traceback" not in err, err
    assert main(["sweep", str(scene), "--out", str(tmp_path / "o")]) == 2
    assert "--design FILE" in capsys.readouterr().err


def test_what_cannot_be_batched_runs_per_run_and_says_why(tmp_path, capsys):
    # the bundled scene has [expect] checks; with method projection: one run each
    code = main(["sweep", str(PARAMETRIC), "--vary", "parameters.m1=[1.0, 1.5]", "--set",
                 "simulate.t_end=0.2", "--set", "simulate.method=projection", "--out", str(tmp_path / "p")])
    out = capsys.readouterr().out
    assert code == 0
    assert "0 batched" in out and "2 one run each" in out and "method 'projection'" in out
    assert "ran in-process: " in out


def test_auto_starts_a_local_cluster_when_the_estimate_is_large(scene, batched, tmp_path, monkeypatch):
    pytest.importorskip("distributed")
    monkeypatch.setattr(sweep_execute, "DASK_WORTH_S", 0.0)
    monkeypatch.setattr(sweep_execute, "_idle_cores", lambda: 1.0)  # other jobs use the cores
    busy = S.sweep(scene, RANDOM, samples=12, seed=5, summary=SUMMARY, out_dir=tmp_path / "busy",
                   progress=False, chunk_size=5, figure=False, workers=2, batch=False)
    assert busy.where.mode == "in-process" and "busy" in busy.where.reason
    monkeypatch.setattr(sweep_execute, "_idle_cores", lambda: 2.0)
    monkeypatch.setattr(sweep_execute, "available_cores", lambda: 2)
    monkeypatch.setattr(sweep_execute, "MIN_THREAD_COLUMNS", 1)  # chunks of 5 and 2: two threads each
    # batched chunks use the cores here already (simulate_many's threads): no cluster for them
    here = S.sweep(scene, RANDOM, samples=12, seed=5, summary=SUMMARY, out_dir=tmp_path / "here",
                   progress=False, chunk_size=5, figure=False, workers=2)
    assert here.where.mode == "in-process" and "share their variants out" in here.where.reason
    _compare(here.rows, batched.rows, 0.0)
    # runs one at a time do go to worker processes
    r = S.sweep(scene, RANDOM, samples=12, seed=5, summary=SUMMARY, out_dir=tmp_path / "spread",
                progress=False, chunk_size=5, figure=False, workers=2, batch=False)
    assert r.where.mode == "local cluster" and r.where.workers == 2 and "above 0 s" in r.where.reason
    _compare(r.rows, batched.rows, 1e-9)  # the per-run numbers on the cluster's workers


def test_ctrl_c_stops_a_batched_sweep_keeps_its_finished_chunks_and_exits_130(scene, tmp_path):
    out = tmp_path / "stopped"
    vary = ["parameters.m1=lin(0.5, 2, 6)"]
    sets = ["simulate.t_end=400", "simulate.output_dt=100"]
    args = ["sweep", str(scene), "--vary", vary[0], "--set", sets[0], "--set", sets[1], "--chunk-size", "2",
            "--out", str(out), "--scheduler", "sequential", "--quiet"]
    code, seconds, err = interrupt_when(args, lambda: bool(_chunk_files(out)), cwd=tmp_path, timeout=120)
    assert code == 130, err
    assert seconds < 10.0 and "Traceback" not in err
    kept = [r for p in _chunk_files(out) for r in pq.read_table(p).to_pylist()]
    assert 2 <= len(kept) < 6 and all(r["status"] == "ok" for r in kept)
    assert (out / "summary.csv").is_file()
    again = S.sweep(scene, vary, overrides=sets, out_dir=out, progress=False, limit=0, chunk_size=2,
                    figure=False)
    assert again.skipped == len(kept) and not again.complete


def test_a_failing_variant_of_a_batched_chunk_is_a_failed_row_and_the_others_finish(scene, tmp_path, capsys):
    """g = 1e300 overflows that variant's forces: its row says so (no numbers), the other
    variants of the same simulate_many call finish with their own, physical results."""
    code = main(["sweep", str(scene), "--vary", "parameters.g=[4.0, 1e300, 16.0]", "--set",
                 "simulate.t_end=0.3", "--out", str(tmp_path), "--quiet"])
    assert code == 0
    assert "1 of 3 runs failed" in capsys.readouterr().err
    rows = list(csv.DictReader(open(tmp_path / "summary.csv")))
    assert [r["path"] for r in rows] == ["batched"] * 3
    # its own run's words: when, and the effect that overflows (gravity at 1e300 m/s²)
    assert rows[1]["status"].startswith("non-finite state after t = 0 s") and rows[1]["x_p2"] == ""
    assert "effect 0 ('gravity" in rows[1]["status"]
    assert rows[0]["status"] == rows[2]["status"] == "ok"
    # gravity sets the time scale: with 4x the gravity the same motion runs twice as fast, so
    # the pendulum at g = 16 at t = 0.15 s stands where the one at g = 4 stands at t = 0.3 s
    again = S.sweep(scene, ["parameters.g=[16.0]"], overrides=["simulate.t_end=0.15"],
                    out_dir=tmp_path / "fast", progress=False, figure=False)
    for name in ("x_p1", "y_p1", "x_p2", "y_p2"):
        assert again.rows[0][name] == pytest.approx(float(rows[0][name]), abs=1e-7)


def test_expect_checks_of_a_batched_sweep_equal_the_per_run_ones(tmp_path):
    """The bundled scene's [expect] (energy drift, residual, rods' lengths = l1, l2 at the end)
    evaluated from the Ensemble: the same values and verdicts as each run's check_expectations,
    and the rods keep the lengths each variant gives them."""
    sets = ["simulate.method=\"dopri\"", "simulate.t_end=1.0", "simulate.output_dt=0.1"]
    vary = ["parameters.l2=[0.7, 1.3]", "parameters.m1=[0.8, 1.6]"]
    kw = dict(overrides=sets, progress=False, figure=False)
    batched = S.sweep(PARAMETRIC, vary, out_dir=tmp_path / "b", **kw)
    per_run = S.sweep(PARAMETRIC, vary, out_dir=tmp_path / "p", batch=False, scheduler="sequential", **kw)
    assert batched.batched == 4 and per_run.per_run == 4
    assert batched.columns == per_run.columns
    _compare(batched.rows, per_run.rows, 1e-9)
    checks = [c for c in batched.columns if c.startswith("expect.") and not c.endswith(".ok")]
    assert len(checks) == 4
    for row in batched.rows:
        assert all(row[f"{c}.ok"] is True for c in checks)
        lengths = [c for c in checks if "x_p2 - x_p1" in c]
        assert row[lengths[0]] < 1e-9  # |p2 - p1| = l2 of this variant at the end
