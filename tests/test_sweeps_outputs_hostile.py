"""The third hostile audit (session 14): sweeps, ensembles and outputs used the way a demanding
user would. Each test that is not marked as a guard failed before its fix (docs/hard-cases.md,
"Hostile input, third audit (session 14)")."""

from __future__ import annotations

import csv
import json
import warnings
from pathlib import Path

import numpy as np
import pytest

import constrained as C
from constrained.cli.main import main
from constrained.errors import InputError
from constrained.sweeps import sweep as sweep_module

ROOT = Path(__file__).resolve().parents[1]

#: A pendulum whose length, gravity and mass are parameters (the start follows the length).
PENDULUM = """
[parameters]
l = 1.0
g = 9.81
m = 1.0

[[particles]]
name = "bob"
mass = "m"
position = ["l", 0, 0]

[[constraints]]
type = "distance"
a = "bob"
point = [0, 0, 0]
length = "l"

[[effects]]
type = "gravity"
g = [0, "-g", 0]

[simulate]
t_end = 0.3
"""


@pytest.fixture
def scene(tmp_path) -> Path:
    path = tmp_path / "pendulum.toml"
    path.write_text(PENDULUM)
    return path


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


# --- sweeps ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("values", ["[1, nan]", "[1, inf]", "[1, -1e400]", "[1, 'abc']", "[1, true]"])
def test_a_listed_parameter_value_no_run_can_use_is_refused_before_anything_runs(scene, tmp_path, capsys,
                                                                                   values):
    out = tmp_path / "out"
    code = main(["sweep", str(scene), "--vary", f"parameters.l={values}", "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "value 2" in err and "Traceback" not in err
    assert not out.exists()


def test_a_nan_inside_a_listed_position_is_refused_too(scene, tmp_path, capsys):
    code = main(["sweep", str(scene), "--vary", "particles.bob.position=[[1, 0, 0], [nan, 0, 0]]",
                 "--out", str(tmp_path / "out"), "--quiet"])
    assert code == 2 and "not a finite number" in capsys.readouterr().err


def test_a_sweep_with_failing_runs_finishes_the_others_and_says_why_per_row(scene, tmp_path, capsys):
    """Guard, and the fix of the batched path's reason for a mass of 0 (it said "inconsistent
    start"): rod lengths 0 and -1, masses 0 and -1 fail, each with its reason; the rest finish."""
    out = tmp_path / "out"
    assert main(["sweep", str(scene), "--vary", "parameters.l=[1, 0, -1, 2]",
                 "--vary", "parameters.m=[1, 0, -1]", "--out", str(out), "--quiet"]) == 0
    assert "runs failed" in capsys.readouterr().err
    rows = _rows(out / "summary.csv")
    assert len(rows) == 12
    for row in rows:
        l, m = float(row["parameters.l"]), float(row["parameters.m"])
        if m <= 0:
            assert "mass" in row["status"] and "positive" in row["status"]
        elif l <= 0:
            assert row["status"] != "ok"
        else:
            assert row["status"] == "ok" and np.isfinite(float(row["x_bob"]))


def test_per_run_failures_name_the_cause(scene, tmp_path):
    """Guard: the per-run path reports each run's own scene error in its row."""
    out = tmp_path / "out"
    assert main(["sweep", str(scene), "--vary", "parameters.l=[1, 0, 1e300]", "--per-run", "--out", str(out),
                 "--quiet"]) == 0
    status = [r["status"] for r in _rows(out / "summary.csv")]
    assert status[0] == "ok"
    assert "starts on the point" in status[1]
    assert "overflow" in status[2] and "starts on the point" not in status[2]


def test_a_start_of_huge_coordinates_is_named_as_overflow_not_as_a_particle_on_its_anchor(scene, tmp_path,
                                                                                       capsys):
    assert main(["check", str(scene), "--set", "parameters.l=1e300"]) == 2
    err = capsys.readouterr().err
    assert "overflow" in err and "starts on the point" not in err


def test_an_interrupted_rerun_leaves_one_table_not_an_older_parquet_and_figure_beside_it(scene, tmp_path,
                                                                                         monkeypatch, capsys):
    out = tmp_path / "out"
    vary = ["particles.bob.mass=lin(0.5, 2, 8)"]  # numbers: one run per chunk, per run
    first = sweep_module.sweep(scene, vary, out_dir=out, limit=2, progress=False, scheduler="sequential")
    assert first.finished == 2 and (out / "sweep.png").is_file() and (out / "summary.parquet").is_file()
    real = sweep_module.execute

    def interrupted_after_three(chunks, record, *args, **kwargs):
        seen = []

        def counting(chunk, result):
            record(chunk, result)
            seen.append(chunk)
            if len(seen) == 3:
                raise KeyboardInterrupt
        return real(chunks, counting, *args, **kwargs)

    monkeypatch.setattr(sweep_module, "execute", interrupted_after_three)
    code = main(["sweep", str(scene), "--vary", vary[0], "--out", str(out), "--quiet",
                 "--scheduler", "sequential"])
    err = capsys.readouterr().err
    assert code == 130 and "5 of 8 runs" in err and "run the same command again" in err
    csv_rows = _rows(out / "summary.csv")
    assert len(csv_rows) == 5
    if (out / "summary.parquet").exists():
        import pyarrow.parquet as pq

        assert pq.read_table(out / "summary.parquet").num_rows == 5
    assert not (out / "sweep.png").exists()  # the figure of the 2-row table is gone
    state = json.loads((out / "sweep.json").read_text())
    assert state["finished"] == 5 and state["total"] == 8 and state["complete"] is False
    monkeypatch.setattr(sweep_module, "execute", real)
    done = sweep_module.sweep(scene, vary, out_dir=out, progress=False, scheduler="sequential")
    assert done.computed == 3 and done.complete and (out / "sweep.png").is_file()
    assert json.loads((out / "sweep.json").read_text())["complete"] is True


def test_a_sweep_of_300_small_runs_is_one_table(scene, tmp_path):
    """Guard: batched, one chunk file, one row per run."""
    r = sweep_module.sweep(scene, ["parameters.l=lin(0.5, 2, 300)"], out_dir=tmp_path / "out", progress=False,
                           figure=False)
    assert r.finished == 300 and r.failed == 0
    assert len(_rows(tmp_path / "out" / "summary.csv")) == 300


def test_unicode_particle_names_can_be_set_and_varied(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text(PENDULUM.replace('"bob"', '"ballé"').replace('[parameters]', '[parameters]\n"λ" = 2.0'))
    assert main(["check", str(path), "--set", "particles.ballé.mass=2", "--set", "parameters.λ=3"]) == 0
    r = sweep_module.sweep(path, ["particles.ballé.velocity=[[0, 0, 0], [0, 1, 0]]"], out_dir=tmp_path / "o",
                           progress=False, figure=False)
    assert r.finished == 2 and r.failed == 0


# --- ensembles ------------------------------------------------------------------------------------


def _system(tmp_path):
    path = tmp_path / "p.toml"
    path.write_text(PENDULUM)
    return C.load_scene(path).system


@pytest.mark.parametrize("column, words", [
    ([1.0, "abc"], "row 1"), ([1.0, None], "row 1"), ([True, False], "row 0"), ([1 + 2j], "row 0"),
    ([[1.0, 2.0], [3.0, 4.0]], "flat list"),
])
def test_simulate_many_refuses_a_column_that_is_not_numbers(tmp_path, column, words):
    with pytest.raises(InputError, match=words):
        C.simulate_many(_system(tmp_path), 0.1, {"l": column})


def test_simulate_many_takes_numpy_numbers_and_refuses_a_nan_correction(tmp_path):
    system = _system(tmp_path)
    e = C.simulate_many(system, np.int64(1), {"l": np.array([1, 2])})
    assert e.ok.all()
    with pytest.raises(InputError, match="max_initial_correction"):
        C.simulate_many(system, 0.1, {"l": [1.0]}, max_initial_correction=float("nan"))


def test_simulate_many_reports_a_mass_that_is_not_positive_as_such(tmp_path):
    e = C.simulate_many(_system(tmp_path), 0.2, {"m": [1.0, 0.0, -1.0]})
    assert e.status == ("completed", "non-positive mass", "non-positive mass")
    assert np.isnan(e.x[1:]).all() and np.isfinite(e.x[0]).all()


def test_simulate_with_parameters_making_a_rod_of_length_zero_names_the_constraint(tmp_path):
    with pytest.raises(InputError, match="undefined at the initial state"):
        C.simulate(_system(tmp_path), 0.1, parameters={"l": 0.0})


# --- outputs --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def saved(tmp_path_factory) -> dict:
    folder = tmp_path_factory.mktemp("run")
    path = folder / "p.toml"
    path.write_text(PENDULUM + '\n[outputs]\nquantities = ["energy", "multipliers"]\n')
    assert main(["run", str(path), "--out", str(folder / "out"), "--quiet"]) == 0
    with np.load(folder / "out" / "trajectory.npz") as data:
        return {k: data[k] for k in data.files}


def _damaged(tmp_path: Path, saved: dict, **changes) -> Path:
    arrays = {**saved, **changes}
    path = tmp_path / "damaged.npz"
    np.savez(path, **arrays)
    return path


def test_plot_refuses_times_that_go_backwards(tmp_path, saved, capsys):
    path = _damaged(tmp_path, saved, t=saved["t"][::-1].copy())
    assert main(["plot", str(path), "--out", str(tmp_path / "p"), "--quiet"]) == 2
    assert "go backwards" in capsys.readouterr().err
    assert main(["view", str(path), "--out", str(tmp_path / "v.html"), "--quiet"]) == 2


def test_plot_refuses_particle_names_that_do_not_match_the_positions(tmp_path, saved, capsys):
    meta = json.loads(str(saved["meta"]))
    meta["particle_names"] = ["a", "b", "c"]
    path = _damaged(tmp_path, saved, meta=np.array(json.dumps(meta)))
    assert main(["plot", str(path), "--out", str(tmp_path / "p"), "--quiet"]) == 2
    assert "names 3 particle(s)" in capsys.readouterr().err


def test_plot_says_when_a_saved_quantity_is_not_finite(tmp_path, saved, capsys):
    path = _damaged(tmp_path, saved, energy=np.full_like(saved["energy"], np.nan))
    assert main(["plot", str(path), "--out", str(tmp_path / "p"), "--kinds", "energy"]) == 0
    out = capsys.readouterr().out
    assert "energy:" in out and "not finite" in out and "(it is empty)" in out


def test_plot_of_enormous_positions_prints_no_numpy_warning(tmp_path, saved, capfd):
    path = _damaged(tmp_path, saved, x=saved["x"] * 1e300)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        assert main(["plot", str(path), "--out", str(tmp_path / "p"), "--kinds", "phase", "--quiet"]) == 0
    assert "RuntimeWarning" not in capfd.readouterr().err


def test_view_into_a_path_under_a_file_names_the_file(tmp_path, saved, capsys):
    path = _damaged(tmp_path, saved)
    (tmp_path / "afile").write_text("x")
    assert main(["view", str(path), "--out", str(tmp_path / "afile" / "v.html"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "is a file, not a folder" in err and "File exists" not in err


def test_plot_and_view_of_one_free_particle_and_of_a_path_with_spaces(tmp_path, capsys):
    """Guard: an unconstrained one-particle run, written and drawn under a name with a space and
    an accent."""
    path = tmp_path / "free.toml"
    path.write_text('[[particles]]\nname = "solo"\nmass = 1.0\nposition = [0, 0, 0]\nvelocity = [1, 0, 0]\n'
                    "[simulate]\nt_end = 0.1\n")
    out = tmp_path / "o ü"
    assert main(["run", str(path), "--out", str(out), "--quiet"]) == 0
    assert main(["plot", str(out), "--out", str(out / "plots"), "--kinds", "trajectory", "--quiet"]) == 0
    assert main(["view", str(out / "trajectory.npz"), "--out", str(out / "v.html"), "--quiet"]) == 0
    assert (out / "plots" / "trajectory.png").is_file() and (out / "v.html").is_file()
