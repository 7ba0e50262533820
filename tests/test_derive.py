"""Checks of hand derivations: candidate Lagrangians, generalized forces, the ``derive`` verb."""

from __future__ import annotations

import pytest
from conftest import SCENARIOS

import constrained as C
from constrained.analysis.derivation import check_generalized_forces, check_lagrangian
from constrained.cli.main import main
from constrained.run.reduced import ReducedModel
from constrained.scene.load import build_scene

DOUBLE = str(SCENARIOS / "double_pendulum.toml")
PARAMS = {"g": 9.81, "m": 1.0, "l": 1.0}
# ERRATA 1: the printed double-pendulum Lagrangian is right.
L_DOUBLE = ("0.5*m*l**2*(2*th1_dot**2 + th2_dot**2 + 2*th1_dot*th2_dot*cos(th1-th2))"
            " + m*g*l*(2*cos(th1) + cos(th2))")
# ERRATA 1: the corrected equations (g/l = g for l = 1) and the printed, wrong pair.
CORRECTED = [
    "2*th1_ddot + th2_ddot*cos(th1-th2) + th2_dot**2*sin(th1-th2) + 2*g*sin(th1) = 0",
    "th2_ddot + th1_ddot*cos(th1-th2) - th1_dot**2*sin(th1-th2) + g*sin(th2) = 0",
]
PRINTED = [
    "-th1_dot*th2_dot*sin(th1-th2) - 2*g*sin(th1) = "
    "th1_ddot + 2*th2_ddot*cos(th1-th2) - 2*th2_dot*sin(th1-th2)*(th1_dot - th2_dot)",
]


@pytest.fixture(scope="module")
def double_pendulum():
    return ReducedModel.from_scene(C.load_scene(SCENARIOS / "double_pendulum.toml"), parameters=PARAMS)


def _hanging_spring(damping=True):
    """A mass on a vertical line, hung from a spring at the origin; X measured downward (y = −X)."""
    effects = [{"type": "gravity", "g": [0, -9.81, 0]},
               {"type": "spring", "a": "m", "point": [0, 0, 0], "k": 5.0}]
    if damping:
        effects.append({"type": "damping", "coefficient": 0.3})
    raw = {"scene": {"name": "hanging spring"},
           "particles": [{"name": "m", "mass": 2.0, "position": [0.0, -0.5, 0.0]}],
           "constraints": [{"type": "plane", "particles": ["m"], "normal": [1, 0, 0]},
                           {"type": "plane", "particles": ["m"], "normal": [0, 0, 1]}],
           "effects": effects,
           "parameters": {"m": 2.0, "g": 9.81, "k": 5.0, "b": 0.3},
           "simulate": {"t_end": 1.0},
           "reduced": {"coordinates": ["X"], "initial": {"X": 0.5}, "map": {"m": ["0", "-X", "0"]}}}
    return build_scene(raw)


def _pendulum():
    raw = {"scene": {"name": "pendulum"},
           "particles": [{"name": "bob", "mass": 1.5, "position": [0.0, -2.0, 0.0]}],
           "constraints": [{"type": "distance", "a": "bob", "point": [0, 0, 0], "length": 2.0},
                           {"type": "plane", "particles": ["bob"], "normal": [0, 0, 1]}],
           "effects": [{"type": "gravity", "g": [0, -9.81, 0]}],
           "parameters": {"m": 1.5, "g": 9.81, "l": 2.0},
           "simulate": {"t_end": 1.0},
           "reduced": {"coordinates": ["th"], "initial": {"th": 0.3},
                       "map": {"bob": ["l*sin(th)", "-l*cos(th)", "0"]}}}
    return build_scene(raw)


# --- candidate Lagrangians ---------------------------------------------------------------------


def test_printed_double_pendulum_lagrangian_is_right(double_pendulum):
    check = check_lagrangian(double_pendulum, L_DOUBLE)
    assert check.ok and check.relative_residual < 1e-12, check.message
    assert "generates the derived equations" in check.message


def test_multiples_and_total_derivatives_are_right(double_pendulum):
    # F(q, t) = t*th1*th2: dF/dt = t*(th1_dot*th2 + th1*th2_dot) + th1*th2
    dF = "t*(th1_dot*th2 + th1*th2_dot) + th1*th2"
    for text in (f"2*({L_DOUBLE})", f"L = {L_DOUBLE} + {dF}", f"-0.5*({L_DOUBLE}) + 3*cos(th1)*th1_dot"):
        check = check_lagrangian(double_pendulum, text)
        assert check.ok, check.message


def test_wrong_double_pendulum_lagrangian_names_the_equation(double_pendulum):
    wrong = L_DOUBLE.replace("2*cos(th1)", "cos(th1)")
    check = check_lagrangian(double_pendulum, wrong)
    assert not check.ok and check.relative_residual > 0.01
    assert "Euler–Lagrange equation for th1" in check.message
    assert "th1 =" in check.message and "th2_dot =" in check.message and "t =" in check.message
    assert set(check.state) >= {"th1", "th2", "th1_dot", "th2_dot", "th1_ddot", "th2_ddot", "t"}


def test_degenerate_lagrangian_is_refused(double_pendulum):
    for text in ("th1_dot*cos(th2) + th2_dot*sin(th1) + cos(th1)", "0.5*th1_dot**2 + cos(th2)"):
        check = check_lagrangian(double_pendulum, text)
        assert not check.ok
        assert "degenerate Lagrangian: no q̈ in its equations" in check.message


def test_damped_hanging_spring_printed_lagrangian_is_wrong():
    scene = _hanging_spring()
    printed = check_lagrangian(scene, "0.5*m*X_dot**2 + m*g*X + 0.5*k*X**2")  # V = −m g x − ½ k x²
    assert not printed.ok and "for X" in printed.message and "damping" in printed.message
    corrected = check_lagrangian(scene, "0.5*m*X_dot**2 + m*g*X - 0.5*k*X**2")  # ERRATA 3
    assert corrected.ok, corrected.message
    # with a given Rayleigh function only the matching scale of L gives the same motion
    assert not check_lagrangian(scene, "2*(0.5*m*X_dot**2 + m*g*X - 0.5*k*X**2)").ok
    assert check_lagrangian(_hanging_spring(damping=False), "3*(0.5*m*X_dot**2 + m*g*X - 0.5*k*X**2)").ok


def test_lagrangian_unknown_name_or_acceleration(double_pendulum):
    with pytest.raises(C.InputError, match="unknown name 'th3_dot'"):
        check_lagrangian(double_pendulum, "th3_dot**2")
    with pytest.raises(C.InputError, match="unknown name 'th1_ddot'"):
        check_lagrangian(double_pendulum, "th1_ddot*th1")
    with pytest.raises(C.InputError, match="L = formula"):
        check_lagrangian(double_pendulum, "T = th1_dot**2")


# --- generalized forces ----------------------------------------------------------------------


def test_pendulum_generalized_force():
    scene = _pendulum()
    (right,) = check_generalized_forces(scene, ["-m*g*l*sin(th)"])
    assert right.ok, right.message
    (wrong,) = check_generalized_forces(scene, ["m*g*l*sin(th)"])
    assert not wrong.ok and "Q_th" in wrong.message and "derived Q_th" in wrong.message
    assert "th =" in wrong.message and "gravity" in wrong.message


def test_damped_spring_generalized_force():
    scene = _hanging_spring()
    (right,) = check_generalized_forces(scene, ["-k*X - b*X_dot + m*g"])
    assert right.ok, right.message
    (wrong,) = check_generalized_forces(scene, ["-k*X + b*X_dot + m*g"])
    assert not wrong.ok and "damping" in wrong.message


def test_double_pendulum_generalized_forces(double_pendulum):
    checks = check_generalized_forces(double_pendulum, ["-2*m*g*l*sin(th1)", "m*g*l*sin(th2)"])
    assert [c.ok for c in checks] == [True, False]
    with pytest.raises(C.InputError, match="one generalized force per coordinate"):
        check_generalized_forces(double_pendulum, ["0"])


# --- the derive verb --------------------------------------------------------------------------

SETS = ["--set", "parameters.g=9.81", "--set", "parameters.m=1", "--set", "parameters.l=1"]


def test_cli_derive_describes(capsys):
    assert main(["derive", DOUBLE]) == 0
    out = capsys.readouterr().out
    assert "L = " in out and "equation for th1" in out


def test_cli_derive_corrected_equations_exit_0(capsys):
    args = ["derive", DOUBLE, *SETS, "--lagrangian", L_DOUBLE]
    for eq in CORRECTED:
        args += ["--equation", eq]
    args += ["--force=-2*m*g*l*sin(th1)", "--force=-m*g*l*sin(th2)"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert out.count("OK:") == 5 and "WRONG" not in out


def test_cli_derive_printed_equation_exit_1(capsys):
    assert main(["derive", DOUBLE, *SETS, "--equation", PRINTED[0]]) == 1
    out = capsys.readouterr().out
    assert "WRONG" in out and "equation 1" in out and "disagrees with Lagrange's equations" in out


def test_cli_derive_unknown_symbol_exit_2(capsys):
    assert main(["derive", DOUBLE, *SETS, "--equation", "th3_ddot = 0"]) == 2
    err = capsys.readouterr().err
    assert "unknown name 'th3_ddot'" in err and "Traceback" not in err
    assert main(["derive", DOUBLE, *SETS, "--force", "0"]) == 2
    assert "one generalized force per coordinate" in capsys.readouterr().err
