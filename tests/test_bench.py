"""constrained bench: the three outputs and what they must contain (never timings)."""

from __future__ import annotations

import csv

import numpy as np
from conftest import SCENARIOS

from constrained.cli.main import main


def test_bench_writes_csv_markdown_and_figure(tmp_path):
    out = tmp_path / "bench"
    code = main(["bench", str(SCENARIOS / "double_pendulum.toml"), "--set", "simulate.t_end=0.5",
                 "--methods", "projection,ggl,rattle", "--tolerances", "1e-6,1e-10", "--repeats", "1",
                 "--out", str(out), "--quiet"])
    assert code == 0
    rows = list(csv.DictReader((out / "bench.csv").open()))
    assert {"method", "rtol", "error", "constraint_residual", "wall_time_s", "steps"} <= set(rows[0])
    assert [r["method"] for r in rows] == ["projection"] * 2 + ["ggl"] * 2 + ["rattle"] * 2
    proj = [r for r in rows if r["method"] == "projection"]
    # tighter tolerance, smaller error, more steps; projection keeps |f| at round-off
    assert float(proj[1]["error"]) < 1e-3 * float(proj[0]["error"])
    assert int(proj[1]["steps"]) > int(proj[0]["steps"])
    assert all(float(r["constraint_residual"]) < 1e-12 for r in proj)
    rattle = [r for r in rows if r["method"] == "rattle"]
    assert np.isclose(float(rattle[0]["dt"]), 1e-2) and float(rattle[1]["error"]) < float(rattle[0]["error"])
    assert all(r["status"] == "ok" for r in rows)
    assert (out / "bench.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    md = (out / "bench.md").read_text()
    assert "| projection | 1e-06 |" in md and "reference" in md


def test_bench_refuses_unknown_methods(tmp_path, capsys):
    code = main(["bench", str(SCENARIOS / "double_pendulum.toml"), "--methods", "euler",
                 "--out", str(tmp_path / "b")])
    assert code == 2
    assert "unknown method" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()


def test_bench_uses_a_declared_closed_form_as_its_reference(tmp_path):
    out = tmp_path / "spring"
    code = main(["bench", str(SCENARIOS / "simple_spring.toml"), "--set", "simulate.t_end=2",
                 "--methods", "projection", "--tolerances", "1e-6,1e-11", "--repeats", "1",
                 "--out", str(out), "--quiet"])
    assert code == 0
    # only the position closed form (x_m) is the reference, not the velocity one (vx_m)
    assert "the scene's closed form for x_m;" in (out / "bench.md").read_text()
    rows = list(csv.DictReader((out / "bench.csv").open()))
    # against x = A cos(ωt − δ) itself: error falls with the tolerance, to the closed form's level
    assert float(rows[1]["error"]) < 1e-9 < float(rows[0]["error"])


def test_bench_on_a_scene_without_expectations(tmp_path):
    from conftest import ROOT

    out = tmp_path / "penning"
    code = main(["bench", str(ROOT / "benchmarks" / "scenes" / "penning.toml"), "--set", "simulate.t_end=0.5",
                 "--methods", "projection", "--tolerances", "1e-8", "--repeats", "1", "--out", str(out),
                 "--quiet"])
    assert code == 0
    (row,) = csv.DictReader((out / "bench.csv").open())
    assert row["status"] == "ok" and float(row["error"]) < 1e-6


def test_bench_reports_progress_for_a_method_with_a_base(tmp_path, capsys):
    out = tmp_path / "bench"
    code = main(["bench", str(SCENARIOS / "double_pendulum.toml"), "--set", "simulate.t_end=0.5",
                 "--methods", "dopri:DOPRI5", "--tolerances", "1e-6,1e-9", "--repeats", "1",
                 "--out", str(out)])
    assert code == 0
    assert "dopri:DOPRI5 (rtol 1e-06)" in capsys.readouterr().out
    rows = list(csv.DictReader((out / "bench.csv").open()))
    assert float(rows[1]["error"]) < 1e-3 * float(rows[0]["error"])
    assert all(float(r["constraint_residual"]) < 1e-12 for r in rows)


def test_a_one_time_cost_of_the_first_run_is_its_own_column_not_solver_time(tmp_path, monkeypatch):
    """A step loop compiled on the first run (here: a pause of 0.4 s standing for the C compile,
    whose time varies by machine) goes to compile_time_s; wall_time_s and the figure's time
    axis are a warm run's."""
    import time

    from constrained.analysis import bench

    real, seen = bench.simulate, set()

    def simulate(system, t_end, **kwargs):
        key = (kwargs.get("method"), kwargs.get("rtol"), kwargs.get("dt"))
        if kwargs.get("t_eval") is not None and key not in seen:  # the first timed call of a setting
            seen.add(key)
            time.sleep(0.4)
        return real(system, t_end, **kwargs)

    monkeypatch.setattr(bench, "simulate", simulate)
    out = tmp_path / "bench"
    assert main(["bench", str(SCENARIOS / "double_pendulum.toml"), "--set", "simulate.t_end=0.5",
                 "--methods", "dopri,projection", "--tolerances", "1e-6,1e-9", "--repeats", "2",
                 "--out", str(out), "--quiet"]) == 0
    rows = list(csv.DictReader((out / "bench.csv").open()))
    assert {"method", "rtol", "error", "constraint_residual", "wall_time_s", "steps", "compile_time_s"} \
        <= set(rows[0])
    for row in rows:
        assert float(row["compile_time_s"]) >= 0.35, row   # the pause, counted once
        assert float(row["wall_time_s"]) < 0.3, row         # not in the solver's time
    md = (out / "bench.md").read_text()
    assert "first-run compile [s]" in md and "after a warm-up run" in md


def test_the_reference_run_is_projection_and_leaves_dopris_compile_to_its_own_rows(tmp_path, monkeypatch):
    """The reference is the method the notes name (projection at 1e-13), not the default
    method: run with dopri, it took dopri's one-time C compile (here a pause of 0.4 s standing
    for it), and the dopri rows showed ~0 in the compile column on a cold cache."""
    import time

    from constrained.analysis import bench
    from constrained.codegen import compiled

    real_simulate, real_compile, methods, paused = bench.simulate, compiled.compile_functions, [], []

    def simulate(system, t_end, **kwargs):
        methods.append(kwargs.get("method", "default"))
        return real_simulate(system, t_end, **kwargs)

    def compile_functions(functions, *args, **kwargs):
        if not paused:  # the first compile of this process's measurement: a cold cache
            paused.append(True)
            time.sleep(0.4)
        return real_compile(functions, *args, **kwargs)

    monkeypatch.setattr(bench, "simulate", simulate)
    monkeypatch.setattr(compiled, "compile_functions", compile_functions)
    out = tmp_path / "bench"
    assert main(["bench", str(SCENARIOS / "double_pendulum.toml"), "--set", "simulate.t_end=0.5",
                 "--methods", "dopri", "--tolerances", "1e-6", "--repeats", "1",
                 "--out", str(out), "--quiet"]) == 0
    assert methods[0] == "projection"
    assert "reference: projection at rtol 1e-13" in (out / "bench.md").read_text()
    (row,) = csv.DictReader((out / "bench.csv").open())
    if paused:  # (a machine without a C compiler compiles nothing)
        assert float(row["compile_time_s"]) >= 0.35, row


def test_bench_measures_the_jacobi_integral_of_a_uniformly_rotating_hoop():
    """Bead on a hoop (R = 1 m, m = 1 kg) turning at ω = 4 rad/s about z: T + V is not conserved
    (the motor works), the Jacobi integral J = ½|v|² − ω²(x² + y²) + g z (= T − ω L_z + V) is.
    The drift column measures J, and agrees with J computed by hand from the trajectory."""
    import constrained as C
    from constrained.analysis.bench import work_precision

    scene = C.load_scene(SCENARIOS / "bead_on_rotating_hoop.toml")
    w, g, tol, t_end = 4.0, 9.81, 1e-9, 2.0
    result = work_precision(scene.system, t_end, methods=("projection",), tolerances=(1e-6, tol), repeats=1)
    assert result.conserves_energy and any("Jacobi integral" in n and "ω = 4" in n for n in result.notes)
    tr = C.simulate(scene.system, t_end, method="projection", rtol=tol, atol=tol)
    x, v = np.asarray(tr.x).reshape(len(tr.t), 3), np.asarray(tr.v).reshape(len(tr.t), 3)
    jacobi = 0.5 * np.sum(v**2, axis=1) - w**2 * (x[:, 0] ** 2 + x[:, 1] ** 2) + g * x[:, 2]
    energy = 0.5 * np.sum(v**2, axis=1) + g * x[:, 2]
    scale = abs(jacobi[0])  # about 10 J
    drift = float(np.max(np.abs(jacobi - jacobi[0])))
    row = result.rows[-1]
    assert row["status"] == "ok" and row["rtol"] == tol
    assert row["energy_drift"] <= 100 * tol * scale  # conserved to the tolerance
    assert abs(row["energy_drift"] - drift) <= 1e-3 * drift + 1e-12 * scale  # the same quantity
    assert np.ptp(energy) > 1.0  # while T + V swings by joules: the column does not measure it
    assert result.rows[0]["energy_drift"] > row["energy_drift"]  # looser tolerance, larger drift
