"""Absurd input gets a one-paragraph message naming the file, the key and what is wrong, and
exit status 2, never a traceback (issue 18, item 7)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import casadi as ca
import pytest
from conftest import pendulum_toml

from constrained.cli.main import main
from constrained.errors import ExpressionError
from constrained.model.expressions import MAX_DEPTH, parse

PENDULUM = pendulum_toml(0.01, position=(1.0, 0.0, 0.0), velocity=None)


def cli(capsys, *argv) -> tuple[int, str]:
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err


def one_line(err: str, *fragments: str) -> None:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("constrained: error: "), err
    for fragment in fragments:
        assert fragment in lines[0], err


@pytest.fixture
def scene(tmp_path) -> Path:
    path = tmp_path / "scene.toml"
    path.write_text(PENDULUM)
    return path


@pytest.mark.parametrize("verb", ["check", "run"])
@pytest.mark.parametrize("override, key, words", [
    ("particles.bob.mass=1e308", "particles[0].mass", "too large"),
    ("particles.bob.mass=-1e308", "particles[0].mass", ""),
    ("effects[0].g=[0, -1e200, 0]", "effects[0].g[1]", "too large"),
    ("constraints[0].length=1e150", "constraints[0].length", "too large"),
    ("constraints[0].length=0", "constraints[0].length", "pin"),
    ("constraints[0].length=-1", "constraints[0].length", "positive length"),
    ("particles.bob.position=[0, 0, 0]", "constraints[0]", "starts on the point"),
    ("effects[0].g=[0, '9**9**9**9', 0]", "effects[0].g[1]", "too large"),
    ("effects[0].g=[0, '10.0**400', 0]", "effects[0].g[1]", "too large"),
    ("effects[0].g=[0, '1/0', 0]", "effects[0].g[1]", "divides by zero"),
    ("effects[0].g=[0, '1e999', 0]", "effects[0].g[1]", "too large"),
    ("effects[0].g=[0, 'exp(1000)', 0]", "effects[0].g[1]", "not a finite number"),
    ("effects[0].g=[0, '" + "-" * 100_000 + "9.81', 0]", "effects[0].g[1]", "characters long"),
    ("effects[0].g=[0, '" + "-" * 5_000 + "9.81', 0]", "effects[0].g[1]", "nested"),
    ("effects[0].g=[0, '" + "(" * 300 + "1" + ")" * 300 + "', 0]", "effects[0].g[1]", "nested"),
    ("effects[0].g=[0, '" + "sin(" * 150 + "t" + ")" * 150 + "', 0]", "effects[0].g[1]", "nested"),
    ("particles.bob.mass=5e-324", "particles[0].mass", "too small"),
    ("simulate.samples=9223372036854775807", "simulate.samples", "1000000"),
    ("simulate.output_dt=1e-300", "simulate.output_dt", "1000000"),
    ("simulate.dt=1e-300", "simulate.dt", "steps"),
    ("simulate.t_start=-1e100", "simulate.t_start", "resolve a time step"),
])
def test_absurd_numbers_and_formulas_are_refused_in_one_line(capsys, scene, tmp_path, verb, override,
                                                             key, words):
    extra = ["--out", tmp_path / "out", "--quiet"] if verb == "run" else []
    code, err = cli(capsys, verb, scene, "--set", override, *extra)
    assert code == 2
    one_line(err, f"scene file {scene}", f"key {key}", words)
    assert len(err) < 2000  # the formula is not echoed in full
    assert not (tmp_path / "out").exists()


def test_two_particles_on_one_spot_joined_by_a_rod_are_refused(capsys, scene):
    text = PENDULUM.replace('[[constraints]]', '[[particles]]\nname = "b2"\nmass = 1.0\n'
                            'position = [1.0, 0.0, 0.0]\n\n[[constraints]]\ntype = "distance"\n'
                            'a = "bob"\nb = "b2"\nlength = 1.0\n\n[[constraints]]', 1)
    scene.write_text(text)
    code, err = cli(capsys, "check", scene)
    assert code == 2
    one_line(err, "key constraints[0]", "'bob' and 'b2' start at the same position")


def test_a_singular_potential_at_the_start_is_refused(capsys, scene):
    scene.write_text(PENDULUM + '\n[[effects]]\ntype = "central"\na = "bob"\npoint = [1, 0, 0]\n'
                     'expr = "1/r"\n')
    code, err = cli(capsys, "check", scene)
    assert code == 2
    one_line(err, "key effects[1]", "not finite", "starts on the point")


TANGENT = """\
[[particles]]
name = "p1"
mass = 1.0
position = [0.0, 0.0, 1.0]

[[constraints]]
type = "surface"
particles = ["p1"]
expr = "x**2 + y**2 + z**2 - 1.0"

[[constraints]]
type = "distance"
a = "p1"
point = [0.0, 1.0, 0.0]
length = 2

[simulate]
t_end = 0.001
"""


def test_constraints_that_only_touch_are_refused_not_a_casadi_traceback(capsys, scene, tmp_path):
    # a sphere of radius 1 and a rod of length 2 from (0, 1, 0) meet in the single point
    # (0, -1, 0): the manifold's minimum-norm projection reaches it (no CasADi error on the
    # singular J M⁻¹ Jᵀ), 1.41 m away from the given start, and run refuses that move
    scene.write_text(TANGENT)
    code, err = cli(capsys, "run", scene, "--out", tmp_path / "out")
    assert code == 2
    one_line(err, f"scene file {scene}", "too far from the constraints", "distance p1", "1.41 m")
    assert not (tmp_path / "out").exists()
    code = main(["check", str(scene)])
    out = capsys.readouterr()
    assert code == 0 and "Traceback" not in out.out + out.err
    assert "projection would move positions by 1.41 m (MORE than the allowed" in out.out


@pytest.mark.parametrize("text, words", [
    ("x" + "**x" * (MAX_DEPTH + 5), "nested"),
    ("-" * 100_000 + "x", "characters long"),
    ("9**9**9**9", "too large"),
    ("(-8)**(1/3)", "not a real number"),
    ("1" + "0" * 5000, "cannot read"),
])
def test_the_parser_refuses_what_would_crash_it(text, words):
    with pytest.raises(ExpressionError, match=words) as info:
        parse(text, {"x": ca.SX.sym("x")}, where="effects[0].expr")
    assert "effects[0].expr" in str(info.value)


def test_long_flat_sums_are_no_nesting():
    x = ca.SX.sym("x")
    expr = parse("+".join(["x"] * 1500), {"x": x})
    assert float(ca.evalf(ca.substitute(expr, x, 2.0))) == 3000.0
    assert float(parse("2**10 - 3 - 4", {})) == 1017.0


@pytest.mark.parametrize("damage", ["truncate", "garbage", "array"])
def test_plot_of_a_damaged_trajectory_file_is_refused(capsys, scene, tmp_path, damage):
    out = tmp_path / "out"
    assert main(["run", str(scene), "--out", str(out), "--quiet"]) == 0
    npz = out / "trajectory.npz"
    data = npz.read_bytes()
    if damage == "truncate":
        npz.write_bytes(data[: len(data) // 2])
    elif damage == "garbage":
        npz.write_bytes(b"not an archive")
    else:
        import numpy as np
        with open(npz, "wb") as f:
            np.save(f, np.zeros(3))
    capsys.readouterr()
    code, err = cli(capsys, "plot", npz, "--out", tmp_path / "figs")
    assert code == 2
    one_line(err, str(npz), "not a readable trajectory file", "run the scene again")


@pytest.mark.parametrize("vary", [["parameters.k=lin(0.1, 1, 1e8)"],
                                  ["parameters.k=lin(0.1, 1, 1000)", "parameters.c=log(1, 10, 1000)"]])
def test_a_sweep_design_beyond_the_limit_is_refused_at_once(tmp_path, vary):
    path = tmp_path / "scene.toml"
    path.write_text(PENDULUM + "\n[parameters]\nk = 1.0\nc = 1.0\n")
    argv = ["sweep", str(path), "--limit", "1", "--scheduler", "sequential", "--out", str(tmp_path / "sw")]
    for v in vary:
        argv += ["--vary", v]
    root = Path(__file__).resolve().parents[1]
    proc = subprocess.run([sys.executable, "-m", "constrained.cli", *argv], capture_output=True, text=True,
                          timeout=60, env={**os.environ, "PYTHONPATH": str(root)})
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    one_line(proc.stderr, "100000", "more than")
    assert not (tmp_path / "sw").exists()


@pytest.mark.parametrize("verb", ["check", "run", "statics"])
def test_with_reduced_coordinates_the_particle_start_is_checked_by_the_verbs_that_use_it(capsys, scene,
                                                                                          tmp_path, verb):
    # the particle positions of a scene with [reduced] may be placeholders for crosscheck's
    # mapped start; the verbs that start from them refuse a singular one
    scene.write_text(PENDULUM.replace("position = [1.0, 0.0, 0.0]", "position = [0.0, 0.0, 0.0]")
                     + '\n[reduced]\ncoordinates = ["th"]\ninitial = { th = 1.0 }\n'
                     'map = { bob = ["sin(th)", "-cos(th)", "0"] }\n')
    from constrained.scene.load import load_scene

    assert load_scene(scene).reduced is not None  # loads: crosscheck can use it
    extra = ["--out", tmp_path / "out"] if verb != "check" else []
    code, err = cli(capsys, verb, scene, *extra)
    assert code == 2
    one_line(err, f"scene file {scene}", "key constraints[0]", "starts on the point")
    assert not (tmp_path / "out").exists()


def _rope_toml(n: int, *, rod_end: str | None = None, potential: str | None = None) -> str:
    text = "".join(f'[[particles]]\nname = "p{i}"\nmass = 0.01\nposition = [{0.01 * (i + 1)}, 0, 0]\n'
                   for i in range(n))
    text += '[[constraints]]\ntype = "distance"\na = "p0"\npoint = [0, 0, 0]\nlength = 0.01\n'
    ends = [f"p{i - 1}" for i in range(1, n)]
    ends[-1] = rod_end or ends[-1]
    text += "".join(f'[[constraints]]\ntype = "distance"\na = "{a}"\nb = "p{i}"\nlength = 0.01\n'
                    for i, a in enumerate(ends, 1))
    if potential:
        text += f'[[effects]]\ntype = "potential"\nexpr = "{potential}"\n'
    return text + "[simulate]\nt_end = 0.01\n"


def test_a_large_scene_s_refusals_name_a_few_particles_not_all(tmp_path, capsys):
    """A 2,000-bead rope with one misspelt particle, one unknown name in a formula, and a run
    viewed with another scene: each refusal names the cause in a line, not the 2,000 particles
    (or 6,000 coordinate names) it used to list; the count, the first names and the last
    remain, and the suggestion for the typo."""
    n = 2000
    bad = tmp_path / "typo.toml"
    bad.write_text(_rope_toml(n, rod_end="p19q7"))
    assert main(["check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "unknown particle 'p19q7'" in err and f"p{n - 1}: {n} in all" in err and "did you mean" in err
    assert len(err) < 600
    formula = tmp_path / "formula.toml"
    formula.write_text(_rope_toml(n, potential="0.1*yp5"))
    assert main(["check", str(formula)]) == 2
    err = capsys.readouterr().err
    assert "unknown name 'yp5'" in err and f"{3 * n + 1} in all" in err and len(err) < 600
    assert "did you mean 'y_p5'?" in err
    good = tmp_path / "rope.toml"
    good.write_text(_rope_toml(n))
    other = tmp_path / "other.toml"
    other.write_text(_rope_toml(n).replace('name = "p7"', 'name = "q7"').replace('"p7"', '"q7"'))
    assert main(["run", str(good), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    page = str(tmp_path / "v.html")
    assert main(["view", str(tmp_path / "out"), "--scene", str(other), "--out", page]) == 2
    err = capsys.readouterr().err
    assert "the first to differ is number 8: 'q7' against 'p7'" in err and len(err) < 600
