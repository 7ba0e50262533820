"""Fits on measurement files nobody here chose (session 18).

Values of 1e308 in a CSV were read, and the fit wandered to l = nan, b = nan and was reported as
"the fit reached l = nan, b = nan, where the run fails … start nearer the solution": the
squares of the residuals overflow. They are now refused where they stand. A file with as many
values as fitted parameters (one row of x, y for l and b) printed standard errors of nan and
"reduced nan" without a word: with no σ given, σ is estimated from the residuals, which leave no
degree of freedom; the report now says so and what to give.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

import constrained as C
from constrained.analysis.fitting.measurements import Measurements
from constrained.cli.main import main
from constrained.errors import InputError

ROOT = Path(__file__).resolve().parents[1]
SCENE = str(ROOT / "scenarios" / "pendulum_fit.toml")
CAMERA = ROOT / "scenarios" / "data" / "pendulum_camera.csv"


def _rows() -> tuple[list[str], list[list[str]]]:
    rows = list(csv.reader(CAMERA.open()))
    return rows[0], rows[1:]


def _write(path: Path, header, body) -> str:
    path.write_text("\n".join(",".join(r) for r in [header, *body]) + "\n")
    return str(path)


def test_a_value_whose_square_overflows_is_refused_naming_its_line(tmp_path, capsys):
    header, body = _rows()
    body[0][1] = "1e308"
    data = _write(tmp_path / "huge.csv", header, body)
    code = main(["fit", SCENE, data, "--params", "l,b", "--out", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2
    assert "line 2, column 'x_bob': 1e+308 is too large to fit" in err and "nan" not in err


def test_measurements_given_in_python_refuse_it_too():
    with pytest.raises(InputError, match=r"row 1 \(from 0\): the value of 'x_p', 1e\+200, is too large"):
        Measurements(t=[0.0, 1.0], names=("x_p",), values=[[1.0], [1e200]])


def test_as_many_values_as_parameters_says_why_the_errors_are_unknown(tmp_path):
    header, body = _rows()
    data = C.read_measurements(_write(tmp_path / "one_row.csv", header, body[60:61]))  # t = 2 s
    scene = C.load_scene(SCENE).system  # one x and one y, for l and b
    result = C.fit(scene, data, ["l", "b"])
    assert result.dof == 0 and np.all(np.isnan(result.standard_errors))
    assert ("standard errors unknown: 2 measured values for 2 fitted parameters leave no degree of "
            "freedom to estimate σ from the residuals; give --sigma") in result.table()
    with_sigma = C.fit(scene, data, ["l", "b"], sigma=1e-3)
    assert np.all(np.isfinite(with_sigma.standard_errors))
    assert "standard errors unknown" not in with_sigma.table()


def test_a_mass_with_only_gravity_is_not_determined_and_no_self_correlation_is_reported(tmp_path, capsys):
    """An undamped pendulum's motion does not depend on its mass: m is reported as not determined,
    and the only other parameter, l, has no correlation to report (it printed "l–l +1.000")."""
    code = main(["fit", SCENE, str(CAMERA), "--params", "m,l", "--set", "parameters.m=0.2",
                 "--set", 'particles[0].mass="m"', "--set", "parameters.b=0", "--out", str(tmp_path / "out")])
    out = capsys.readouterr().out
    assert code == 0
    assert "NOT determined by these data: 1·m + 0·l" in out
    assert "largest correlation" not in out
