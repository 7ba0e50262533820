"""The reduced route: Lagrange's equations in q against the Cartesian route, derivation checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import DP_ENERGY, DP_REF_T2, SCENARIOS

import constrained as C
from constrained.analysis.crosscheck import cross_check
from constrained.analysis.derivation import check_equations, conservation, describe
from constrained.cli.main import main
from constrained.run.reduced import ReducedModel
from constrained.scene.load import build_scene

TIGHT = {"rtol": 1e-11, "atol": 1e-12}


def _scene(particles, constraints=(), effects=(), reduced=None, parameters=None, t_end=1.0):
    raw = {"scene": {"name": "test"}, "particles": list(particles), "constraints": list(constraints),
           "effects": list(effects), "simulate": {"t_end": t_end}, "reduced": reduced}
    if parameters:
        raw["parameters"] = parameters
    return build_scene(raw)


def _line_x():
    return [{"type": "plane", "particles": ["m"], "normal": [0, 1, 0]},
            {"type": "plane", "particles": ["m"], "normal": [0, 0, 1]}]


def _plane_z(name="m"):
    return [{"type": "plane", "particles": [name], "normal": [0, 0, 1]}]


def _particle(name="m", mass=1.0):
    return {"name": name, "mass": mass, "position": [0.0, 0.0, 0.0]}


def _agree(scene, t_end, tol=1e-8, **kw):
    cc = cross_check(scene, t_end, samples=101, **TIGHT, **kw)
    assert cc.max_position_difference < tol, cc.table()
    return cc


# --- both routes on the theory text's examples ----------------------------------------------


def test_spring_both_routes_and_closed_form():
    sc = _scene([_particle()], _line_x(), [{"type": "spring", "a": "m", "point": [0, 0, 0], "k": 4.0}],
                {"coordinates": ["s"], "initial": {"s": 0.5}, "map": {"m": ["s", "0", "0"]}})
    cc = _agree(sc, 3.0)
    q = cc.reduced.info["q"][:, 0]
    assert np.max(np.abs(q - 0.5 * np.cos(2.0 * cc.t))) < 1e-9


def test_simple_pendulum_both_routes():
    sc = _scene([_particle("bob")],
                [{"type": "distance", "a": "bob", "point": [0, 0, 0], "length": 1.0}] + _plane_z("bob"),
                [{"type": "gravity", "g": [0, -9.81, 0]}],
                {"coordinates": ["th"], "initial": {"th": 1.0}, "rates": {"th": 0.3},
                 "map": {"bob": ["sin(th)", "-cos(th)", "0"]}})
    cc = _agree(sc, 3.0)
    assert cc.max_constraint_force_difference < 1e-6


def test_kepler_polar_both_routes_momentum_period():
    sc = C.load_scene(SCENARIOS / "kepler.toml")
    E = 0.5 * 1.2**2 - 1.0
    a = 1.0 / (2 * abs(E))
    period = 2 * math.pi * math.sqrt(a**3)
    cc = _agree(sc, period, t_eval=np.linspace(0, period, 101))
    rm = cc.reduced_model
    cons = conservation(rm, cc.reduced)
    assert cons.cyclic == ["phi"]
    assert cons.momentum_drift["phi"] < 1e-10
    assert cons.hamiltonian_conserved and cons.hamiltonian_is_energy
    end = cc.reduced.x[-1, 0]
    assert np.linalg.norm(end - np.array([1.0, 0.0, 0.0])) < 1e-7  # back at the start after T


def test_free_particle_both_routes_and_cyclic():
    sc = _scene([{"name": "m", "mass": 2.0, "position": [0, 0, 0]}], (), (),
                {"coordinates": ["qx", "qy", "qz"], "initial": {"qx": 0, "qy": 1, "qz": 0},
                 "rates": {"qx": 1.0, "qy": -0.5, "qz": 0.25}, "map": {"m": ["qx", "qy", "qz"]}})
    cc = _agree(sc, 2.0)
    cons = conservation(cc.reduced_model, cc.reduced)
    assert "qx" in cons.cyclic and cons.structurally_cyclic == ["qx", "qy", "qz"]
    assert cons.momentum_drift["qx"] < 1e-14


def test_double_pendulum_scene_chaotic_start_two_seconds():
    sc = C.load_scene(SCENARIOS / "double_pendulum.toml")
    cc = _agree(sc, 2.0)
    assert np.max(np.abs(cc.reduced.x[-1, :, :2] - DP_REF_T2)) < 1e-8
    assert np.max(np.abs(cc.cartesian.energy - DP_ENERGY)) < 1e-7


def test_double_pendulum_twenty_seconds_regular_start():
    sc = C.load_scene(SCENARIOS / "double_pendulum.toml",
                      ["reduced.initial.th1=0.3", "reduced.initial.th2=-0.2"])
    _agree(sc, 20.0)


def test_charged_particle_uniform_field_polar():
    B, qc, m = 2.0, 1.5, 1.0
    sc = _scene([_particle()], _plane_z(),
                [{"type": "electromagnetic", "charges": {"m": qc}, "A": ["-0.5*B*y", "0.5*B*x", "0"]}],
                {"coordinates": ["rho", "phi"], "initial": {"rho": 1.0, "phi": 0.0},
                 "rates": {"rho": 0.2, "phi": 0.7}, "map": {"m": ["rho*cos(phi)", "rho*sin(phi)", "0"]}},
                parameters={"B": B})
    cc = _agree(sc, 3.0)
    # a uniform B turns the velocity at the cyclotron frequency q B / m; the speed is constant
    v = cc.reduced.v[:, 0, :]
    speed = np.linalg.norm(v, axis=1)
    assert np.max(np.abs(speed - speed[0])) < 1e-9
    angle = np.unwrap(np.arctan2(v[:, 1], v[:, 0]))
    assert np.max(np.abs((angle - angle[0]) + qc * B / m * cc.t)) < 1e-8


def test_damped_hanging_spring_closed_form():
    m, b, k, g = 1.0, 0.4, 9.0, 9.81
    sc = _scene([_particle()],
                [{"type": "plane", "particles": ["m"], "normal": [1, 0, 0]}] + _plane_z(),
                [{"type": "spring", "a": "m", "point": [0, 0, 0], "k": k},
                 {"type": "gravity", "g": [0, -g, 0]},
                 {"type": "damping", "coefficient": b}],
                {"coordinates": ["s"], "initial": {"s": 0.2}, "rates": {"s": 0.0},
                 "map": {"m": ["0", "-s", "0"]}})  # s measured downward
    cc = _agree(sc, 5.0)
    gam, s_eq = b / (2 * m), m * g / k
    wd = math.sqrt(k / m - gam**2)
    u0 = 0.2 - s_eq
    t = cc.t
    exact = s_eq + np.exp(-gam * t) * (u0 * np.cos(wd * t) + gam * u0 / wd * np.sin(wd * t))
    assert np.max(np.abs(cc.reduced.info["q"][:, 0] - exact)) < 1e-9
    assert not conservation(cc.reduced_model).hamiltonian_conserved


def test_bead_on_rotating_hoop_jacobi_integral():
    sc = C.load_scene(SCENARIOS / "bead_on_rotating_hoop.toml")
    cc = _agree(sc, 5.0)
    cons = conservation(cc.reduced_model, cc.reduced)
    assert cc.reduced_model.rheonomic
    assert cons.hamiltonian_conserved and not cons.hamiltonian_is_energy
    assert cons.hamiltonian_drift < 1e-9
    assert cons.energy_drift > 1e-2  # T + V is not conserved: the motor does work
    assert cons.cyclic == []


# --- hand-derivation checks ------------------------------------------------------------------

# The theory text's printed pair (m = l = 1), with its d/dt expanded by the chain rule.
PRINTED = [
    "-th1_dot*th2_dot*sin(th1-th2) - 2*g*sin(th1) = "
    "th1_ddot + 2*th2_ddot*cos(th1-th2) - 2*th2_dot*sin(th1-th2)*(th1_dot - th2_dot)",
    "th1_dot*th2_dot*sin(th1-th2) - g*sin(th2) = "
    "th2_ddot + 2*th1_ddot*cos(th1-th2) - 2*th1_dot*sin(th1-th2)*(th1_dot - th2_dot)",
]
CORRECTED = [  # ERRATA 1
    "2*th1_ddot + th2_ddot*cos(th1-th2) + th2_dot**2*sin(th1-th2) + 2*g*sin(th1) = 0",
    "th2_ddot + th1_ddot*cos(th1-th2) - th1_dot**2*sin(th1-th2) + g*sin(th2) = 0",
]


@pytest.fixture(scope="module")
def double_pendulum_model():
    return ReducedModel.from_scene(C.load_scene(SCENARIOS / "double_pendulum.toml"), parameters={"g": 9.81})


def test_printed_double_pendulum_equations_are_flagged(double_pendulum_model):
    for check in C.check_equations(double_pendulum_model, PRINTED):
        assert not check.ok and check.relative_residual > 0.01
        assert "disagrees with Lagrange's equations" in check.message and "th1 =" in check.message


def test_corrected_equations_and_combinations_pass(double_pendulum_model):
    combo = f"3*({CORRECTED[0].split('=')[0]}) - cos(th1)*({CORRECTED[1].split('=')[0]})"
    scaled = "-(4*th2_ddot + 4*th1_ddot*cos(th1-th2)) = -4*th1_dot**2*sin(th1-th2) + 4*g*sin(th2)"
    sign_error = "-(4*th2_ddot + 4*th1_ddot*cos(th1-th2)) = 4*th1_dot**2*sin(th1-th2) + 4*g*sin(th2)"
    checks = check_equations(double_pendulum_model, [*CORRECTED, combo, scaled, sign_error])
    assert [c.ok for c in checks] == [True, True, True, True, False]
    assert all(c.residual < 1e-10 for c in checks[:4])


def test_identity_is_not_an_equation_of_motion(double_pendulum_model):
    (check,) = check_equations(double_pendulum_model, "sin(th1)**2 + cos(th1)**2 = 1")
    assert not check.ok and "identity" in check.message


def test_unknown_symbol_in_equation(double_pendulum_model):
    with pytest.raises(C.InputError, match="unknown name 'th3_ddot'"):
        check_equations(double_pendulum_model, ["th3_ddot = 0"])


def test_describe_prints_lagrangian():
    sc = _scene([_particle()], _line_x(), [{"type": "spring", "a": "m", "point": [0, 0, 0], "k": 4.0}],
                {"coordinates": ["s"], "initial": {"s": 0.5}, "map": {"m": ["s", "0", "0"]}})
    text = describe(sc)
    assert "L = " in text and "s_dot^2" in text and "equation for s" in text


# --- bad input -------------------------------------------------------------------------------


def _pendulum_system():
    s = C.System(name="pendulum")
    s.add_particle("bob", 1.0, [1.0, 0.0, 0.0])
    s.add(C.Distance("bob", point=[0, 0, 0], length=1.0), C.Plane("bob", [0, 0, 1]), C.Gravity([0, -9.81, 0]))
    return s


def test_map_violating_a_constraint_is_refused():
    with pytest.raises(C.InputError, match=r"violates constraint 0 \(distance.*by"):
        ReducedModel(_pendulum_system(), ["th"], {"bob": ["2*sin(th)", "-cos(th)", "0"]}, initial={"th": 0.5})


def test_wrong_number_of_coordinates_is_refused():
    with pytest.raises(C.InputError, match="too many coordinates"):
        ReducedModel(_pendulum_system(), ["a", "b"], {"bob": ["sin(a)", "-cos(a)", "0"]})
    free = C.System([C.Particle("m", 1.0, [0, 0, 0])])
    with pytest.raises(C.InputError, match="too few coordinates"):
        ReducedModel(free, ["a"], {"m": ["a", "0", "0"]})
    with pytest.raises(C.InputError, match="dependent"):
        ReducedModel(free, ["a", "b", "c"], {"m": ["a + b", "c", "0*a"]})


def test_cli_crosscheck(tmp_path, capsys):
    out = tmp_path / "out"
    code = main(["crosscheck", str(SCENARIOS / "double_pendulum.toml"), "--out", str(out),
                 "--set", "simulate.t_end=0.5"])
    assert code == 0
    assert (out / "crosscheck.png").is_file()
    assert "max position difference" in capsys.readouterr().out


def test_cli_crosscheck_bad_map_exit_2(tmp_path, capsys):
    out = tmp_path / "out"
    code = main(["crosscheck", str(SCENARIOS / "double_pendulum.toml"), "--out", str(out),
                 "--set", "simulate.t_end=0.5",
                 "--set", 'reduced.map.p2=["sin(th1) + sin(th2)", "-cos(th1) - 2*cos(th2)", "0"]'])
    assert code == 2
    err = capsys.readouterr().err
    assert "reduced.map" in err and "violates constraint" in err and "Traceback" not in err
    assert not out.exists()


def test_describe_prints_the_double_pendulum_equations_in_readable_form():
    from constrained.analysis.derivation import pretty

    scene = C.load_scene(SCENARIOS / "double_pendulum.toml")
    text = C.describe(scene)
    # the corrected equations of ERRATA item 1, with g/l = 9.81 and both sides times 2 for θ1
    assert ("equation for th1: 2*th1_ddot + th2_ddot*cos(th1 - th2) + th2_dot^2*sin(th1 - th2)"
            " + 19.62*sin(th1) = 0") in text
    assert "p_th2 = th1_dot*cos(th1 - th2) + th2_dot" in text
    raw = pretty(C.ReducedModel.from_scene(scene).expressions["p"][1], simplify=False)
    assert "cos(th1 - th2)" not in raw  # CasADi's own graph is not simplified
