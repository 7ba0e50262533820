"""The ``constrained`` command: run, check, and one-paragraph errors with exit status 2."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import BLOWUP_TOML, pendulum_toml

from constrained.cli.main import main
from constrained.run.options import time_grid
from constrained.run.trajectory import Trajectory

ROOT = Path(__file__).resolve().parents[1]
DOUBLE_PENDULUM = ROOT / "scenarios" / "double_pendulum.toml"

PENDULUM = pendulum_toml(0.5)


def write(tmp_path: Path, text: str, name: str = "scene.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def assert_one_paragraph_error(stderr: str, *fragments: str) -> None:
    assert "Traceback" not in stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith("constrained: error: "), stderr
    for fragment in fragments:
        assert fragment in lines[0], stderr


# --- run -------------------------------------------------------------------------------------


def test_run_double_pendulum_writes_requested_arrays_and_plots(tmp_path, capsys):
    out = tmp_path / "out"
    code = main(["run", str(DOUBLE_PENDULUM), "--out", str(out), "--set", "simulate.t_end=0.5"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    with np.load(out / "trajectory.npz") as data:
        arrays = {k: data[k] for k in data.files if k != "meta"}
    assert set(arrays) == {"t", "x", "v", "multipliers", "constraint_forces", "energy", "constraint_residual"}
    assert arrays["t"][-1] == pytest.approx(0.5)
    assert arrays["x"].shape[1:] == (2, 3) and arrays["multipliers"].shape[1] == 4
    assert np.max(arrays["constraint_residual"]) <= 1e-10
    assert np.ptp(arrays["energy"]) < 1e-6
    for kind in ("trajectory", "energy", "constraint_residual"):
        assert (out / f"{kind}.png").stat().st_size > 0
    assert "double pendulum" in captured.out and "degrees of freedom 2" in captured.out
    assert "max constraint residual" in captured.out


def test_run_csv_and_chosen_quantities(tmp_path, capsys):
    out = tmp_path / "res"
    scene = write(tmp_path, PENDULUM)
    code = main(
        [
            "run",
            str(scene),
            "--out",
            str(out),
            "--quiet",
            "--set",
            'outputs.formats=["npz", "csv"]',
            "--set",
            'outputs.quantities=["multipliers", "velocity_residual"]',
            "--set",
            "simulate.samples=11",
        ]
    )
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert captured.out == ""
    with np.load(out / "trajectory.npz") as data:
        assert set(data.files) - {"meta"} == {"t", "x", "v", "multipliers", "velocity_residual"}
        np.testing.assert_allclose(data["t"], np.linspace(0.0, 0.5, 11))
    lines = (out / "trajectory.csv").read_text().splitlines()
    header = next(csv.reader(lines[:1]))
    assert header[:4] == ["t", "x_bob", "y_bob", "z_bob"]
    assert header[-2].startswith("lambda[distance bob") and header[-1] == "velocity_residual"
    assert len(lines) == 12
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == []  # no temporary files


def test_run_default_out_dir_is_out_slash_stem(tmp_path, monkeypatch):
    scene = write(tmp_path, PENDULUM, "swing.toml")
    monkeypatch.chdir(tmp_path)
    assert main(["run", "swing.toml", "--quiet"]) == 0
    assert (tmp_path / "out" / "swing" / "trajectory.npz").is_file()
    assert scene.is_file()


def test_run_that_has_to_stop_saves_partial_trajectory(tmp_path, capsys):
    text = BLOWUP_TOML
    out = tmp_path / "out"
    code = main(["run", str(write(tmp_path, text)), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 1
    assert_one_paragraph_error(err, "stopped", "trajectory.npz")
    with np.load(out / "trajectory.npz") as data:
        assert 0 < data["t"][-1] < 3.0


# --- check -----------------------------------------------------------------------------------


def test_check_double_pendulum(capsys):
    assert main(["check", str(DOUBLE_PENDULUM)]) == 0
    out = capsys.readouterr().out
    assert "degrees of freedom 2" in out and "rank 4" in out
    assert "redundant constraints: none" in out
    assert "configuration: regular" in out
    assert "distance p1–p2 = 1 m" in out
    assert "plane n=(0, 0, 1), offset 0 [p2]" in out
    assert "projection would move positions by" in out
    assert "model terms: constraints, potential" in out


def test_check_names_redundant_constraint(tmp_path, capsys):
    text = PENDULUM + '\n[[constraints]]\ntype = "plane"\nparticles = "bob"\nnormal = [0, 0, 1]\n'
    text += '\n[[constraints]]\ntype = "custom"\nexpr = "2*z_bob"\nname = "twice the plane"\n'
    assert main(["check", str(write(tmp_path, text))]) == 0
    out = capsys.readouterr().out
    assert "degrees of freedom 1" in out
    assert "redundant constraints: twice the plane" in out


def test_check_reports_singular_configuration(tmp_path, capsys):
    text = '[[particles]]\nname = "p"\nmass = 1.0\nposition = [0.0, 0.0, 0.0]\n'
    for x in (-1, 1):
        text += f'[[constraints]]\ntype = "distance"\na = "p"\npoint = [{x}, 0, 0]\nlength = 1\n'
    assert main(["check", str(write(tmp_path, text))]) == 0
    out = capsys.readouterr().out
    assert "rank 1 (generic rank 2), degrees of freedom 2 (1 away from this configuration)" in out
    assert "configuration: SINGULAR" in out


def test_check_of_a_large_scene_lists_the_first_items_and_counts_the_rest(tmp_path, capsys):
    """A 60-bead chain hanging from a point, each rod stated twice (redundant rows of their
    own): the listing stops at LISTED particles, rows and redundant rows and says how many
    more there are; the summary is the whole scene's (3·60 − 60 = 120 degrees of freedom);
    --all lists every one."""
    from constrained.cli.text import LISTED

    n = 60
    text = "".join(f'[[particles]]\nname = "p{i}"\nmass = 0.01\nposition = [{0.01 * (i + 1)}, 0, 0]\n'
                   for i in range(n))
    text += '[[constraints]]\ntype = "distance"\na = "p0"\npoint = [0, 0, 0]\nlength = 0.01\n'
    for _ in range(2):
        text += "".join(f'[[constraints]]\ntype = "distance"\na = "p{i - 1}"\nb = "p{i}"\nlength = 0.01\n'
                        for i in range(1, n))
    path = write(tmp_path, text)
    assert main(["check", str(path)]) == 0
    out = capsys.readouterr().out
    assert "degrees of freedom 120" in out and "constraint rows 119, rank 60" in out
    assert f"p{LISTED - 1}: mass" in out and f"p{LISTED}: mass" not in out
    assert f"… {n - LISTED} more particles (--all lists them)" in out
    assert f"… {2 * n - 1 - LISTED} more rows (--all lists them)" in out
    assert f"… {n - 1 - LISTED} more (--all lists them)" in out  # the 59 redundant rods
    assert main(["check", str(path), "--all"]) == 0
    every = capsys.readouterr().out
    assert f"p{n - 1}: mass" in every and f"[{2 * n - 2}] " in every and "more" not in every


def test_help_lists_verbs_with_examples(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "constrained run scenarios/double_pendulum.toml" in out
    assert "constrained check scenarios/double_pendulum.toml" in out


def test_time_grid():
    np.testing.assert_allclose(time_grid(0.0, 1.0, output_dt=0.25), [0, 0.25, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(time_grid(0.0, 1.0, output_dt=0.3), [0, 0.3, 0.6, 0.9, 1.0])
    assert time_grid(0.0, 0.3, output_dt=0.1)[-1] == 0.3
    np.testing.assert_allclose(time_grid(1.0, 2.0, samples=3), [1.0, 1.5, 2.0])
    assert time_grid(0.0, 1.0) is None


# --- bad input: exit 2, one paragraph naming file and key, nothing written -----------------

BAD_CASES = {
    "unknown key": (PENDULUM.replace("mass = 1.0", "mass = 1.0\ncolour = 3"), [], "particles[0].colour"),
    "bad mass": (PENDULUM.replace("mass = 1.0", "mass = -1"), [], "particles[0].mass"),
    "bad --set key": (PENDULUM, ["simulate.t_ned=1"], "simulate.t_ned"),
    "bad --set name": (PENDULUM, ["particles.rob.mass=1"], "particles.rob.mass"),
    "bad formula": (PENDULUM.replace("[0.0, 0.0, 0.0]", '["open(1)", 0, 0]'), [], "constraints[0].point[0]"),
    "no end time": (PENDULUM.replace("t_end = 0.5", ""), [], "simulate.t_end"),
    "inconsistent start": (PENDULUM.replace("length = 1.0", "length = 2.0"), [], "particles"),
}


@pytest.mark.parametrize("case", list(BAD_CASES))
def test_run_bad_input_exits_2_and_writes_nothing(tmp_path, capsys, case):
    text, overrides, key = BAD_CASES[case]
    scene = write(tmp_path, text)
    out = tmp_path / "out"
    argv = ["run", str(scene), "--out", str(out)]
    for o in overrides:
        argv += ["--set", o]
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert_one_paragraph_error(captured.err, f"scene file {scene}", f"key {key}:")
    assert captured.out == ""
    assert not out.exists()


def test_bad_input_leaves_existing_out_dir_as_it_was(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("old")
    scene = write(tmp_path, PENDULUM.replace("length = 1.0", "length = 2.0"))
    assert main(["run", str(scene), "--out", str(out)]) == 2
    assert [p.name for p in out.iterdir()] == ["keep.txt"]


@pytest.mark.parametrize(
    ("argv", "fragment"),
    [
        (["frobnicate", "x.toml"], "invalid choice: 'frobnicate'"),
        (["run"], "SCENE"),
        ([], "VERB"),
        (["check", "missing.toml"], "scene file missing.toml: no such file"),
    ],
)
def test_usage_errors_exit_2_with_one_paragraph(capsys, argv, fragment):
    assert main(argv) == 2
    assert_one_paragraph_error(capsys.readouterr().err, fragment)


def test_check_bad_scene_exits_2(tmp_path, capsys):
    scene = write(tmp_path, PENDULUM.replace('type = "gravity"', 'type = "gravitation"'))
    assert main(["check", str(scene)]) == 2
    assert_one_paragraph_error(capsys.readouterr().err, str(scene), "key effects[0].type:", "gravity")


def _subprocess(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run(
        [sys.executable, "-m", "constrained.cli", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_subprocess_bad_scene_has_no_traceback(tmp_path):
    scene = write(tmp_path, PENDULUM.replace("position = [0.0, -1.0, 0.0]", "position = [0.0, nan, 0.0]"))
    out = tmp_path / "out"
    proc = _subprocess("run", str(scene), "--out", str(out), cwd=tmp_path)
    assert proc.returncode == 2
    assert_one_paragraph_error(proc.stderr, f"scene file {scene}", "key particles[0].position[1]:")
    assert proc.stdout == ""
    assert not out.exists()


def test_subprocess_unknown_verb_and_bad_set(tmp_path):
    proc = _subprocess("simulate", "x.toml", cwd=tmp_path)
    assert proc.returncode == 2
    assert_one_paragraph_error(proc.stderr, "invalid choice")
    scene = write(tmp_path, PENDULUM)
    proc = _subprocess("check", str(scene), "--set", "simulate.rtol", cwd=tmp_path)
    assert proc.returncode == 2
    assert_one_paragraph_error(proc.stderr, f"scene file {scene}", "key simulate.rtol:", "KEY=VALUE")


def test_run_with_the_reduced_method_uses_the_scenes_map(tmp_path):
    from conftest import SCENARIOS

    out = tmp_path / "red"
    code = main(["run", str(SCENARIOS / "double_pendulum.toml"), "--set", "simulate.method=reduced",
                 "--set", "simulate.t_end=2", "--out", str(out), "--quiet"])
    assert code == 0  # the scene's [expect] checks pass through the reduced route too
    tr = Trajectory.load(out / "trajectory.npz")
    assert np.max(tr.constraint_residual) <= 1e-12


def test_reduced_method_without_a_map_and_bad_compiled_setting_are_refused(tmp_path, capsys):
    from conftest import SCENARIOS

    code = main(["run", str(SCENARIOS / "rigid_tetrahedron.toml"), "--set", "simulate.method=reduced",
                 "--out", str(tmp_path / "a")])
    assert code == 2 and "simulate.method" in capsys.readouterr().err
    code = main(["run", str(SCENARIOS / "free_particle.toml"), "--set", "simulate.compiled=maybe",
                 "--out", str(tmp_path / "b")])
    assert code == 2 and "simulate.compiled" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_run_summary_calls_a_damped_energy_loss_a_change_not_a_drift(tmp_path, capsys):
    code = main(["run", str(ROOT / "scenarios" / "damped_hanging_spring.toml"), "--set", "simulate.t_end=1",
                 "--set", "outputs.plots=[]", "--out", str(tmp_path / "damped")])
    out = capsys.readouterr().out
    assert code == 0 and "energy change: E(end) - E0 = -" in out and "energy drift" not in out
    code = main(["run", str(ROOT / "scenarios" / "simple_pendulum.toml"), "--set", "simulate.t_end=4.5",
                 "--set", "outputs.plots=[]", "--out", str(tmp_path / "pendulum")])
    out = capsys.readouterr().out
    assert code == 0 and "energy drift: max |E - E0|" in out


def test_run_summary_gives_no_relative_drift_against_an_energy_that_starts_at_zero(tmp_path, capsys):
    """A rope released horizontal and at rest at the potential's zero (here 1e-18 m above it: E0
    of round-off size, as a cloth's start had): drift / |E0| would be a huge number that says
    nothing (it read 9.8e+23 on a 32 x 32 cloth)."""
    rods = "\n".join(f'[[constraints]]\ntype = "distance"\na = "p{i}"\nb = "p{i + 1}"\nlength = 0.01\n'
                     for i in range(3))
    particles = "\n".join(f'[[particles]]\nname = "p{i}"\nmass = 0.01\nposition = [{0.01 * i}, 1e-18, 0]\n'
                          for i in range(4))
    scene = tmp_path / "rope.toml"
    scene.write_text(f'[scene]\nname = "rope"\n{particles}\n[[constraints]]\ntype = "pin"\na = "p0"\n'
                     f'point = [0, 1e-18, 0]\n{rods}\n[[effects]]\ntype = "gravity"\ng = [0, -9.81, 0]\n'
                     '[simulate]\nt_end = 0.2\n[outputs]\nplots = []\n')
    code = main(["run", str(scene), "--out", str(tmp_path / "out")])
    out = capsys.readouterr().out
    line = next(text for text in out.splitlines() if text.startswith("energy drift"))
    assert code == 0 and "(relative" not in line and "no relative figure" in line, out


def test_the_command_runs_blas_on_one_thread_unless_its_environment_says(tmp_path):
    """constrained.cli sets OPENBLAS_NUM_THREADS=1 before any verb imports NumPy (its pool spins
    between calls: constrained.threads); a value the caller set is kept."""
    code = ("import json, constrained.cli.main, numpy, threadpoolctl; print(json.dumps("
            "[i['num_threads'] for i in threadpoolctl.threadpool_info() if i['user_api'] == 'blas']))")
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")}

    def threads(extra: dict) -> list:
        out = subprocess.run([sys.executable, "-c", code], env={**env, **extra}, capture_output=True,
                             text=True, check=True, cwd=tmp_path)
        return json.loads(out.stdout)

    assert threads({}) == [1] or threads({}) == []  # (no BLAS found by threadpoolctl: nothing to limit)
    if (os.cpu_count() or 1) >= 2 and threads({}):
        assert threads({"OPENBLAS_NUM_THREADS": "2"}) == [2]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_the_command_keeps_freed_blocks_unless_the_environment_tunes_malloc(tmp_path):
    """constrained.cli sets glibc's mmap and trim thresholds (large arrays reused, not mapped
    afresh and faulted in again); a MALLOC_* or GLIBC_TUNABLES setting of the caller wins."""
    code = "import constrained.cli as c; print(c.KEEPS_FREED_BLOCKS)"
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"}

    def kept(extra: dict) -> str:
        return subprocess.run([sys.executable, "-c", code], env={**env, **extra}, capture_output=True,
                              text=True, check=True, cwd=tmp_path).stdout.strip()

    import ctypes

    try:
        ctypes.CDLL(None).mallopt  # noqa: B018 - glibc has it; musl does not
    except AttributeError:
        pytest.skip("no mallopt in this C library")
    assert kept({}) == "True"
    assert kept({"MALLOC_ARENA_MAX": "2"}) == "False"
    assert kept({"GLIBC_TUNABLES": "glibc.malloc.arena_max=2"}) == "False"
