"""`derive` and constants of the motion (docs/hard-cases.md section 19): the conserved quantities
`derive` prints, and `--conserved` / `check_constant_of_motion` on hand-derived candidates.

Every verdict is compared with a hand derivation: the closed-form constants of the motion of the
scene, and dC/dt in closed form at the state (and parameter values) the verdict names, with the
state's accelerations checked against the hand-derived equations of motion.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from conftest import SCENARIOS
from test_derive_unfriendly import _damped_pendulum, _double_residuals

import constrained as C
from constrained.analysis.derivation import check_constant_of_motion, describe_conserved
from constrained.cli.main import main
from constrained.model import expressions
from constrained.scene.load import build_scene

HOOP = SCENARIOS / "bead_on_rotating_hoop.toml"  # m = R = 1, g = 9.81, w = 4 (a parameter)
G = 9.81
# the Jacobi integral h = ½ m R² θ̇² − ½ m R² ω² sin²θ − m g R cos θ (θ from the downward vertical)
HOOP_H = "0.5*th_dot**2 - 0.5*w**2*sin(th)**2 - 9.81*cos(th)"
HOOP_T_PLUS_V = "0.5*th_dot**2 + 0.5*w**2*sin(th)**2 - 9.81*cos(th)"  # T = ½ (θ̇² + ω² sin²θ)
DOUBLE = SCENARIOS / "double_pendulum_parametric.toml"  # m1 = m2 = 1, l1 = l2 = 1
DOUBLE_E = ("0.5*(m1 + m2)*l1**2*q1_dot**2 + 0.5*m2*l2**2*q2_dot**2 + m2*l1*l2*q1_dot*q2_dot*cos(q1 - q2)"
            " - (m1 + m2)*g*l1*cos(q1) - m2*g*l2*cos(q2)")
KEPLER = SCENARIOS / "kepler.toml"  # m = 1, V = −k/ρ, in the plane: (ρ, φ)
KEPLER_E = "0.5*(rho_dot**2 + rho**2*phi_dot**2) - k/rho"
# Laplace–Runge–Lenz A = p × L − m k r̂ (m = 1, L_z = ρ² φ̇), v = (ρ̇ cos φ − ρ φ̇ sin φ, ρ̇ sin φ + ρ φ̇ cos φ)
KEPLER_AX = "(rho_dot*sin(phi) + rho*phi_dot*cos(phi))*rho**2*phi_dot - k*cos(phi)"
KEPLER_AY = "-(rho_dot*cos(phi) - rho*phi_dot*sin(phi))*rho**2*phi_dot - k*sin(phi)"
SLEIGH = SCENARIOS / "chaplygin_sleigh.toml"
# T of the sleigh about its rear point P: M the mass, a = 2 mS b / M the centre of mass from P along the
# axis, I = 2 mS (b² + w²) the moment of inertia about P
SLEIGH_E = "0.5*M*(X_dot**2 + Y_dot**2) + M*a*th_dot*(Y_dot*cos(th) - X_dot*sin(th)) + 0.5*I*th_dot**2"


def _rate(message: str, name: str = "C") -> float:
    """The signed dC/dt a WRONG verdict reports."""
    match = re.search(rf"d{name}/dt = (-?[0-9.]+(?:e[-+]?\d+)?) \(", message)
    assert match, message
    return float(match.group(1))


def _printed(text: str, quantity: str) -> str:
    """The formula printed for ``quantity`` ('h', 'p_ph') in derive's list of conserved quantities,
    in the parser's syntax."""
    match = re.search(rf"^  {re.escape(quantity)} = (.+?)  [(%]", text, re.M)
    assert match, text
    return match.group(1).replace("^", "**").replace("Abs(", "abs(")


def _at(formula: str, **values) -> float:
    return float(expressions.parse(formula, values))


def _spherical(m=0.7, l=1.3):
    """A spherical pendulum with its mass and length as parameters:
    L = ½ m l² (θ̇² + sin²θ φ̇²) + m g l cos θ."""
    raw = {"scene": {"name": "spherical pendulum"},
           "parameters": {"m": m, "l": l, "g": G},
           "particles": [{"name": "bob", "mass": "m",
                          "position": ["l*sin(0.6)", 0.0, "-l*cos(0.6)"],
                          "velocity": [0.0, "2.5*l*sin(0.6)", 0.0]}],
           "constraints": [{"type": "distance", "a": "bob", "point": [0, 0, 0], "length": "l"}],
           "effects": [{"type": "gravity", "g": [0, 0, "-g"]}],
           "simulate": {"t_end": 1.0},
           "reduced": {"coordinates": ["th", "ph"], "initial": {"th": 0.6, "ph": 0.0},
                       "rates": {"th": 0.0, "ph": 2.5},
                       "map": {"bob": ["l*sin(th)*cos(ph)", "l*sin(th)*sin(ph)", "-l*cos(th)"]}}}
    return build_scene(raw)


# --- the rotating hoop: the Jacobi integral, not T + V ---------------------------------------------


def test_hoop_jacobi_integral_is_conserved_and_its_t_plus_v_is_not():
    scene = C.load_scene(HOOP)
    right = check_constant_of_motion(scene, HOOP_H)
    assert right.ok, right.message
    assert "also at 2 other sets of values of w" in right.message and "it is h" in right.message
    wrong = check_constant_of_motion(scene, HOOP_T_PLUS_V)
    assert not wrong.ok
    s = wrong.state
    th, thd, thdd, w = s["th"], s["th_dot"], s["th_ddot"], 4.0
    # the state's acceleration is the hoop's: θ̈ = ω² sin θ cos θ − g sin θ
    assert thdd == pytest.approx(w**2 * math.sin(th) * math.cos(th) - G * math.sin(th), abs=1e-12)
    # T + V = h + m R² ω² sin²θ, so d(T + V)/dt = 2 m R² ω² sin θ cos θ θ̇: the drive's power
    expected = 2 * w**2 * math.sin(th) * math.cos(th) * thd
    assert _rate(wrong.message) == pytest.approx(expected, rel=1e-5)
    assert wrong.residual == pytest.approx(abs(expected), rel=1e-12)
    # the hint: T + V is h plus a remainder, which is m R² ω² sin²θ
    rest = re.search(r"it is h \(.*?\) plus (.+?): h is conserved", wrong.message).group(1)
    for x in (0.3, 1.1, 2.0):
        assert _at(rest.replace("^", "**"), th=x, w=w) == pytest.approx(w**2 * math.sin(x) ** 2, rel=1e-12)
    # 2 h + 3 with w written as 4 is conserved, at w = 4 only
    numbers = check_constant_of_motion(scene, "2*(0.5*th_dot**2 - 0.5*4**2*sin(th)**2 - 9.81*cos(th)) + 3")
    assert numbers.ok and "2 × h + 3" in numbers.message and "right for w = 4 only" in numbers.message
    assert not check_constant_of_motion(scene, numbers.equation, parameters={"w": 5.0}).ok


def test_hoop_printout_gives_its_jacobi_integral_and_the_command_line_checks_it(capsys):
    assert main(["derive", str(HOOP)]) == 0
    out = capsys.readouterr().out
    h = _printed(out, "h")
    rng = np.random.default_rng(5)
    for th, thd, w in rng.uniform(-2, 2, (5, 3)):
        closed = 0.5 * thd**2 - 0.5 * w**2 * math.sin(th) ** 2 - G * math.cos(th)
        assert _at(h, th=th, th_dot=thd, w=w) == pytest.approx(closed, rel=1e-12, abs=1e-12)
    assert "the Jacobi integral" in out and "h ≠ T + V" in out and "T + V is not conserved" in out
    assert "p_th is not conserved: L depends on th" in out
    assert main(["derive", str(HOOP), "--conserved", HOOP_H, "--conserved", HOOP_T_PLUS_V]) == 1
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].startswith("OK: C = ") and lines[2].startswith("WRONG: C = ")
    assert main(["derive", str(HOOP), "--conserved", h]) == 0  # the printed h, fed back


# --- the spherical pendulum: p_φ -------------------------------------------------------------------


def test_spherical_pendulum_azimuthal_momentum():
    shipped = C.load_scene(SCENARIOS / "spherical_pendulum.toml")  # m = l = 1
    assert check_constant_of_motion(shipped, "sin(th)**2*ph_dot").ok
    scene = _spherical()
    right = check_constant_of_motion(scene, "p_ph = m*l**2*sin(th)**2*ph_dot")
    assert right.ok and "it is p_ph" in right.message and "other sets of values of m, l" in right.message
    wrong = check_constant_of_motion(scene, "m*l**2*sin(th)*ph_dot")
    assert not wrong.ok
    s, m, l = wrong.state, 0.7, 1.3
    th, thd, phd = s["th"], s["th_dot"], s["ph_dot"]
    # the state's φ̈ is the pendulum's: d/dt (sin²θ φ̇) = 0
    assert s["ph_ddot"] == pytest.approx(-2 * math.cos(th) / math.sin(th) * thd * phd, rel=1e-9)
    # d/dt (m l² sin θ φ̇) = m l² (cos θ θ̇ φ̇ + sin θ φ̈) = −m l² cos θ θ̇ φ̇
    expected = -m * l**2 * math.cos(th) * thd * phd
    assert _rate(wrong.message) == pytest.approx(expected, rel=1e-5)
    assert wrong.residual == pytest.approx(abs(expected), rel=1e-9)
    text = describe_conserved(scene)
    p = _printed(text, "p_ph")
    for th, phd in ((0.4, 1.5), (2.0, -0.7)):
        closed = m * l**2 * math.sin(th) ** 2 * phd
        assert _at(p, th=th, ph_dot=phd, m=m, l=l) == pytest.approx(closed, rel=1e-12)
    e = _printed(text, "h")
    closed = 0.5 * m * l**2 * (0.3**2 + math.sin(0.8) ** 2 * 1.7**2) - m * G * l * math.cos(0.8)
    assert _at(e, th=0.8, th_dot=0.3, ph_dot=1.7, m=m, l=l, g=G) == pytest.approx(closed, rel=1e-12)
    assert "h = T + V, the energy" in text and "ph is cyclic" in text


# --- Kepler: angular momentum, energy, Laplace–Runge–Lenz ------------------------------------------


def test_kepler_constants_and_a_wrong_sign():
    scene = C.load_scene(KEPLER)
    angular = check_constant_of_motion(scene, "rho**2*phi_dot")
    assert angular.ok and "it is p_phi" in angular.message
    energy = check_constant_of_motion(scene, KEPLER_E)
    assert energy.ok and "it is h" in energy.message
    for component in (KEPLER_AX, KEPLER_AY):
        lenz = check_constant_of_motion(scene, component)
        assert lenz.ok and "not one the tool finds" in lenz.message and "values of k" in lenz.message
    flipped = check_constant_of_motion(scene, KEPLER_AX.replace("- k*cos", "+ k*cos"))
    assert not flipped.ok
    s, k = flipped.state, 1.0
    rho, phi, rd, pd = s["rho"], s["phi"], s["rho_dot"], s["phi_dot"]
    # Kepler's equations at the state: ρ̈ = ρ φ̇² − k/ρ², d/dt (ρ² φ̇) = 0
    assert s["rho_ddot"] == pytest.approx(rho * pd**2 - k / rho**2, rel=1e-9)
    assert s["phi_ddot"] == pytest.approx(-2 * rd * pd / rho, rel=1e-9)
    # A_x + 2 k cos φ: its rate is −2 k sin φ φ̇
    assert _rate(flipped.message) == pytest.approx(-2 * k * math.sin(phi) * pd, rel=1e-5)
    sign = check_constant_of_motion(scene, KEPLER_E.replace("- k/rho", "+ k/rho"))
    assert not sign.ok and "it is h" in sign.message and "plus" in sign.message
    s = sign.state
    # T + k/ρ = h + 2 k/ρ: its rate is −2 k ρ̇/ρ²
    assert _rate(sign.message) == pytest.approx(-2 * k * s["rho_dot"] / s["rho"] ** 2, rel=1e-5)


# --- dissipation and driving: energy not conserved -------------------------------------------------


def test_damped_pendulum_energy_loses_its_dissipation():
    """m l² θ̈ + c l² θ̇ + m g l sin θ = 0: E = ½ m l² θ̇² − m g l cos θ has dE/dt = −c l² θ̇²."""
    scene = _damped_pendulum(c=0.4)
    m, g, l, c = 1.5, 9.81, 2.0, 0.4
    check = check_constant_of_motion(scene, "E = 0.5*m*l**2*th_dot**2 - m*g*l*cos(th)")
    assert not check.ok
    s = check.state
    th, thd = s["th"], s["th_dot"]
    assert m * l**2 * s["th_ddot"] + c * l**2 * thd + m * g * l * math.sin(th) == pytest.approx(0, abs=1e-10)
    assert _rate(check.message, "E") == pytest.approx(-c * l**2 * thd**2, rel=1e-5)
    assert check.residual == pytest.approx(c * l**2 * thd**2, rel=1e-10)
    assert "it is h" in check.message and "not conserved here" in check.message and "damping" in check.message
    text = describe_conserved(scene)
    assert text.startswith("conserved quantities: none found") and "damping" in text


def test_damped_spring_and_driven_pivot_on_the_command_line(capsys):
    spring = str(SCENARIOS / "damped_hanging_spring.toml")  # m s'' + b s' + k s = m g, m = 1, b = 1
    assert main(["derive", spring]) == 0
    out = capsys.readouterr().out
    assert "conserved quantities: none found" in out and "damping" in out
    assert main(["derive", spring, "--conserved", "0.5*s_dot**2 + 0.5*k*s**2 - g*s"]) == 1
    line = capsys.readouterr().out.splitlines()[1]
    state = dict(re.findall(r"(\w+) = (-?[0-9.]+(?:e[-+]?\d+)?)", line.split(" at ", 1)[1]))
    sd = float(state["s_dot"])
    assert _rate(line) == pytest.approx(-1.0 * sd**2, rel=1e-5)  # −b ṡ²
    kapitza = str(SCENARIOS / "kapitza_pendulum.toml")
    assert main(["derive", kapitza]) == 0
    out = capsys.readouterr().out
    assert "conserved quantities: none found" in out and "L depends on t explicitly" in out
    assert "driven pivot" in out


# --- a slip the scene's values hide ----------------------------------------------------------------


def test_energy_right_only_because_l1_equals_l2():
    scene = C.load_scene(DOUBLE)
    assert check_constant_of_motion(scene, DOUBLE_E).ok
    slip = check_constant_of_motion(scene, DOUBLE_E.replace("0.5*m2*l2**2", "0.5*m2*l1**2"))
    assert not slip.ok and "hide a slip" in slip.message and "l1 or l2 alone" in slip.message
    p = dict(scene.system.parameters, **slip.parameters)
    assert p["l1"] != p["l2"]
    s = slip.state
    e1, e2 = _double_residuals(s, p)  # the state's accelerations are the double pendulum's there
    assert abs(e1) < 1e-10 and abs(e2) < 1e-10
    # the slip adds ½ m2 (l1² − l2²) q̇2² to the energy: its rate is m2 (l1² − l2²) q̇2 q̈2
    expected = p["m2"] * (p["l1"] ** 2 - p["l2"] ** 2) * s["q2_dot"] * s["q2_ddot"]
    assert slip.residual == pytest.approx(abs(expected), rel=1e-9)
    assert _rate(slip.message) == pytest.approx(expected, rel=1e-5)


# --- velocity constraints and forces that do no work -----------------------------------------------


def test_chaplygin_sleigh_energy_with_its_knife_edge():
    scene = C.load_scene(SLEIGH)
    energy = check_constant_of_motion(scene, SLEIGH_E)
    assert energy.ok and "q_dot on the velocity constraints" in energy.message
    # on the knife edge P moves along the axis only: T = ½ M v² + ½ I θ̇², v the speed along it
    along = check_constant_of_motion(scene, "0.5*M*(X_dot*cos(th) + Y_dot*sin(th))**2 + 0.5*I*th_dot**2")
    assert along.ok
    # p_X: X is absent from L, but the runner pushes sideways: not conserved
    px = check_constant_of_motion(scene, "M*X_dot - M*a*th_dot*sin(th)")
    assert not px.ok and "it is p_X" in px.message and "velocity constraint acts on X" in px.message
    s = px.state
    assert -s["X_dot"] * math.sin(s["th"]) + s["Y_dot"] * math.cos(s["th"]) == pytest.approx(0, abs=1e-12)
    M, a = 2.0, 0.5  # mP + 2 mS, 2 mS b / M
    th, thd = s["th"], s["th_dot"]
    expected = M * s["X_ddot"] - M * a * (s["th_ddot"] * math.sin(th) + thd**2 * math.cos(th))
    assert _rate(px.message) == pytest.approx(expected, rel=1e-5)
    # and the sideways force is all of it: M a_P^⊥ of the rear point = runner force, along (−sin θ, cos θ)
    dpy = M * s["Y_ddot"] + M * a * (s["th_ddot"] * math.cos(th) - thd**2 * math.sin(th))
    assert expected * math.cos(th) + dpy * math.sin(th) == pytest.approx(0, abs=1e-9)
    text = describe_conserved(scene)
    assert "p_X is not conserved" in text and "the velocity constraints do no work" in text


def test_magnetic_force_given_as_an_applied_force_does_no_work():
    """F = qc B (Ẏ, −Ẋ) on a charge in the plane: h = ½ m v² conserved, p_X not, m Ẋ − qc B Y is."""
    raw = {"scene": {"name": "charge in B, as a force"},
           "parameters": {"qc": 2.0, "B": 1.5, "m": 0.5},
           "particles": [{"name": "ion", "mass": "m", "position": [0.1, 0.2, 0.0]}],
           "constraints": [{"type": "plane", "particles": ["ion"], "normal": [0, 0, 1]}],
           "effects": [{"type": "force", "particle": "ion", "expr": ["qc*B*vy_ion", "-qc*B*vx_ion", "0"]}],
           "simulate": {"t_end": 1.0},
           "reduced": {"coordinates": ["X", "Y"], "initial": {"X": 0.1, "Y": 0.2},
                       "map": {"ion": ["X", "Y", "0"]}}}
    scene = build_scene(raw)
    text = describe_conserved(scene)
    h = _printed(text, "h")
    assert _at(h, X_dot=0.3, Y_dot=-1.1, m=0.5) == pytest.approx(0.25 * (0.3**2 + 1.1**2), rel=1e-12)
    assert "p_X is not conserved" in text and "force on ion" in text
    assert C.ReducedModel.from_scene(scene).jacobi_integral_conserved()  # Q·q̇ = 0, though Q ≠ 0
    assert check_constant_of_motion(scene, "0.5*m*(X_dot**2 + Y_dot**2)").ok
    canonical = check_constant_of_motion(scene, "m*X_dot - qc*B*Y")
    assert canonical.ok and "not one the tool finds" in canonical.message
    wrong = check_constant_of_motion(scene, "m*X_dot")
    assert not wrong.ok and "it is p_X" in wrong.message
    assert _rate(wrong.message) == pytest.approx(2.0 * 1.5 * wrong.state["Y_dot"], rel=1e-5)  # qc B Ẏ


# --- input that cannot be judged ---------------------------------------------------------------------


@pytest.mark.parametrize(("scene", "candidate", "message"), [
    (HOOP, "3", "is trivial: it depends on neither"),
    (HOOP, "sin(th)**2 + cos(th)**2", "is trivial"),
    (HOOP, "t", "a function of t alone is not"),
    (SLEIGH, "Y_dot*cos(th) - X_dot*sin(th) + 2", "takes the same value, 2, at every sampled state"),
    (HOOP, "th_dot + th_ddot", "contains the acceleration th_ddot"),
    (HOOP, "th_dot + R", "unknown name 'R'"),
    (HOOP, "log(th - 5) + th_dot", "is not finite at"),
    (HOOP, "a + b = th_dot", "'NAME = formula'"),
])
def test_bad_constants_exit_2_naming_the_cause(capsys, scene, candidate, message):
    assert main(["derive", str(scene), f"--conserved={candidate}"]) == 2
    assert message in capsys.readouterr().err


def test_latex_printout_of_the_conserved_quantities(capsys):
    pytest.importorskip("sympy")
    assert main(["derive", str(SCENARIOS / "spherical_pendulum.toml"), "--latex"]) == 0
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.strip().startswith("p_{ph} = ") and "%" in x)
    assert r"\sin^{2}" in line and r"\dot{ph}" in line and "ph is cyclic" in line
