"""Statics: equilibrium, reactions, stability and virtual work against closed forms.

Every expected value is computed here, independently of the package (fsolve for the discrete
catenary, numpy for the double Atwood machine, hand-derived potentials for the rest).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import fsolve

import constrained as C
from constrained.analysis.statics import (
    constraint_virtual_work_residual,
    equilibrium,
    generalized_forces,
    virtual_work,
)
from constrained.cli.main import main
from constrained.manifold.manifold import Manifold

ROOT = Path(__file__).resolve().parents[1]
G = 9.81


# --- systems -----------------------------------------------------------------------------------


def chain(n=8, length=0.6, m=0.5, end=(4.0, 1.0)) -> C.System:
    """n masses on n + 1 rods between the anchors (0, 0, 0) and (end, 0), in the plane z = 0."""
    s = C.System(name="chain")
    xs = np.linspace(0.0, end[0], n + 2)[1:-1]
    for i, x in enumerate(xs):  # a rough guess, not on the constraints
        s.add_particle(f"p{i + 1}", m, [x, end[1] * x / end[0] - 1.0, 0.0])
    s.add(C.Distance("p1", point=[0, 0, 0], length=length))
    for i in range(1, n):
        s.add(C.Distance(f"p{i}", f"p{i + 1}", length=length))
    s.add(C.Distance(f"p{n}", point=[end[0], end[1], 0.0], length=length))
    s.add(C.Plane(s.names, [0, 0, 1]), C.Gravity([0, -G, 0]))
    return s


def discrete_catenary(n, length, m, end) -> np.ndarray:
    """Mass positions (n, 2): horizontal tension H constant, the vertical component of the
    rod tension grows by m g at each mass, so rod k (k = 0..n) has tan φ_k = (V0 + k m g)/H."""

    def rods(p):
        H, V0 = p
        phi = np.arctan2(V0 + np.arange(n + 1) * m * G, H)
        return length * np.column_stack([np.cos(phi), np.sin(phi)])

    def miss(p):
        return rods(p).sum(axis=0) - np.asarray(end)

    sol, info, ier, msg = fsolve(miss, [m * G, -n * m * G / 2], xtol=1e-14, full_output=True)
    assert ier == 1, msg
    assert np.max(np.abs(miss(sol))) < 1e-13
    return np.cumsum(rods(sol), axis=0)[:-1]


def lever(m1, m2, a=0.5, b=1.0, h=0.3, mc=0.2, angle=0.0) -> C.System:
    """A rigid planar triangle turning about the fixed pivot O = 0: m1 at distance a on the
    left, m2 at b on the right, a pointer c at distance h below O (a beam balance)."""
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    p1, p2, pc = (rot @ np.array(v) for v in ([-a, 0.0], [b, 0.0], [0.0, -h]))
    s = C.System(name="lever")
    s.add_particle("m1", m1, [*p1, 0.0])
    s.add_particle("m2", m2, [*p2, 0.0])
    s.add_particle("c", mc, [*pc, 0.0])
    s.add(
        C.Distance("m1", point=[0, 0, 0], length=a),
        C.Distance("m2", point=[0, 0, 0], length=b),
        C.Distance("c", point=[0, 0, 0], length=h),
        C.Distance("m1", "c", length=float(np.hypot(a, h))),
        C.Distance("m2", "c", length=float(np.hypot(b, h))),
        C.Plane(["m1", "m2", "c"], [0, 0, 1]),
        C.Gravity([0, -G, 0]),
    )
    return s


def pendulum(theta, m=1.3, l=0.8) -> C.System:
    s = C.System(name="pendulum")
    s.add_particle("bob", m, [l * np.sin(theta), -l * np.cos(theta), 0.0])
    s.add(C.Distance("bob", point=[0, 0, 0], length=l), C.Plane("bob", [0, 0, 1]), C.Gravity([0, -G, 0]))
    return s


def hoop(k, m=0.7, R=0.5, theta=0.0) -> C.System:
    """A bead on the vertical circle |x| = R (plane z = 0), gravity, and a spring of constant k
    and rest length 0 from the bead to the top of the hoop (0, R)."""
    s = C.System(name="hoop")
    s.add_particle("bead", m, [R * np.sin(theta), -R * np.cos(theta), 0.0])
    s.add(
        C.Distance("bead", point=[0, 0, 0], length=R),
        C.Plane("bead", [0, 0, 1]),
        C.Gravity([0, -G, 0]),
        C.Spring("bead", point=[0, R, 0], k=k, rest=0.0),
    )
    return s


def admissible_step(system, eq, size=1e-3) -> np.ndarray:
    """eq.x moved by ``size`` along a tangent direction, then projected back onto f = 0."""
    model = C.assemble(system)
    x = eq.x.ravel() + size * eq.tangent_basis[:, 0]
    projected = Manifold(model).project_positions(x, 0.0, tol=1e-14)
    x = projected.x
    assert projected.residual < 1e-12 and projected.converged
    return x.reshape(-1, 3)


# --- 1. hanging chain --------------------------------------------------------------------------


def test_hanging_chain_is_the_discrete_catenary():
    n, length, m, end = 8, 0.6, 0.5, (4.0, 1.0)
    s = chain(n, length, m, end)
    eq = equilibrium(s)
    expected = discrete_catenary(n, length, m, end)
    assert eq.converged and eq.stable is True
    np.testing.assert_allclose(eq.x[:, :2], expected, atol=1e-8, rtol=0)
    np.testing.assert_allclose(eq.x[:, 2], 0.0, atol=1e-12)
    support = np.sum([f for _, f in eq.anchor_reactions], axis=0)
    assert support[1] == pytest.approx(n * m * G, abs=1e-8)
    assert abs(support[0]) < 1e-8  # the horizontal pulls of the two anchors cancel
    assert eq.virtual_work_residual < 1e-10
    assert eq.constraint_virtual_work_residual < 1e-10
    assert len(eq.eigenvalues) == n - 1 and np.all(eq.eigenvalues > 0)
    # the rods pull: every rod multiplier is a tension (λ = −tension < 0)
    assert np.all(eq.multipliers[: n + 1] < 0)


# --- 2. lever ----------------------------------------------------------------------------------


@pytest.mark.parametrize("m1, m2", [(2.0, 1.0), (1.0, 0.5), (1.0, 1.0), (3.0, 1.0)])
def test_lever_virtual_work_vanishes_iff_moments_balance(m1, m2):
    a, b, h, mc = 0.5, 1.0, 0.3, 0.2
    s = lever(m1, m2, a, b, h, mc)
    w = virtual_work(s, s.positions)
    # one freedom, rotation about O: δx_i = δθ ẑ × r_i, |δx| = δθ sqrt(Σ r_i²), δW = g (m1 a − m2 b) δθ
    expected = G * abs(m1 * a - m2 * b) / np.sqrt(a * a + b * b + h * h)
    if m1 * a == m2 * b:
        assert w < 1e-10
    else:
        assert w > 1.0
        assert w == pytest.approx(expected, rel=1e-12)


def test_lever_pivot_reaction_is_the_total_weight():
    m1, m2, mc = 2.0, 1.0, 0.2
    s = lever(m1, m2, mc=mc)
    eq = equilibrium(s)
    np.testing.assert_allclose(eq.x, s.positions, atol=1e-12)  # balanced: stays horizontal
    assert eq.stable is True  # the pointer hangs below the pivot
    pivot = [f for label, f in eq.anchor_reactions if "(0, 0, 0)" in label]
    assert len(pivot) == 3
    np.testing.assert_allclose(np.sum(pivot, axis=0), [0.0, (m1 + m2 + mc) * G, 0.0], atol=1e-10)


# --- 3. inclined plane -------------------------------------------------------------------------


def test_particle_on_incline_held_by_a_spring():
    m, k, alpha, d, rest = 1.7, 40.0, np.radians(25.0), 2.0, 0.5
    up = np.array([np.cos(alpha), np.sin(alpha), 0.0])
    normal = np.array([-np.sin(alpha), np.cos(alpha), 0.0])
    s = C.System(name="incline")
    s.add_particle("p", m, (d - rest) * up)  # spring at its rest length: not in equilibrium
    s.add(
        C.Plane("p", list(normal), 0.0, name="incline"),
        C.Plane("p", [0, 0, 1], name="z"),
        C.Gravity([0, -G, 0]),
        C.Spring("p", point=list(d * up), k=k, rest=rest),
    )
    eq = equilibrium(s)
    extension = np.linalg.norm(eq.x[0] - d * up) - rest
    assert extension == pytest.approx(m * G * np.sin(alpha) / k, abs=1e-9)
    reaction = dict(eq.anchor_reactions)["incline [p]"]
    np.testing.assert_allclose(reaction, m * G * np.cos(alpha) * normal, atol=1e-9)
    assert np.linalg.norm(reaction) == pytest.approx(m * G * np.cos(alpha), abs=1e-9)
    assert eq.stable is True
    assert eq.eigenvalues == pytest.approx([k], rel=1e-9)  # stiffness along the incline


# --- 4. Atwood machines (dynamics) -------------------------------------------------------------


def _vertical_line(s, name, x):
    s.add(C.Plane(name, [1, 0, 0], x, name=f"line {name}"), C.Plane(name, [0, 0, 1], name=f"z {name}"))


def test_atwood_machine_acceleration_and_tension():
    m1, m2 = 3.0, 1.2
    s = C.System(name="atwood")
    s.add_particle("a", m1, [0.0, -1.0, 0.0])
    s.add_particle("b", m2, [1.0, -1.5, 0.0])
    _vertical_line(s, "a", 0.0)
    _vertical_line(s, "b", 1.0)
    s.add(C.Custom("y_a + y_b + 2.5", name="string"), C.Gravity([0, -G, 0]))
    tr = C.simulate(s, 0.5, rtol=1e-12, atol=1e-12, t_eval=np.linspace(0, 0.5, 6))
    acc = (tr.v[-1, :, 1] - tr.v[0, :, 1]) / (tr.t[-1] - tr.t[0])
    a_expected = G * (m1 - m2) / (m1 + m2)
    np.testing.assert_allclose(acc, [-a_expected, a_expected], atol=1e-9)
    tension = 2 * m1 * m2 * G / (m1 + m2)
    string = tr.constraint_labels.index("string")  # ∂f/∂y_a = 1: the multiplier is the tension
    np.testing.assert_allclose(tr.multipliers[:, string], tension, atol=1e-9)
    np.testing.assert_allclose(tr.constraint_forces[:, 0, 1], tension, atol=1e-9)


def test_double_atwood_machine_acceleration_and_tensions():
    # m1 hangs from a string over a fixed pulley whose other end holds a massless pulley P;
    # m2 and m3 hang from a second string over P. With y_P = c1 − y1 and y2 + y3 − 2 y_P = c2:
    # one constraint 2 y1 + y2 + y3 = c. Its force is 2λ on m1 (tension T1) and λ on m2, m3 (T2).
    m1, m2, m3 = 2.0, 0.7, 1.1
    s = C.System(name="double atwood")
    s.add_particle("m1", m1, [0.0, -1.0, 0.0])
    s.add_particle("m2", m2, [1.0, -2.0, 0.0])
    s.add_particle("m3", m3, [2.0, -1.0, 0.0])
    for i, name in enumerate(s.names):
        _vertical_line(s, name, float(i))
    s.add(C.Custom("2*y_m1 + y_m2 + y_m3 + 5", name="strings"), C.Gravity([0, -G, 0]))
    # textbook equations: m1 a1 = 2T − m1 g, m2 a2 = T − m2 g, m3 a3 = T − m3 g, 2a1 + a2 + a3 = 0
    A = np.array([[m1, 0, 0, -2], [0, m2, 0, -1], [0, 0, m3, -1], [2, 1, 1, 0]], float)
    a1, a2, a3, T = np.linalg.solve(A, [-m1 * G, -m2 * G, -m3 * G, 0.0])
    tr = C.simulate(s, 0.4, rtol=1e-12, atol=1e-12, t_eval=np.linspace(0, 0.4, 5))
    acc = (tr.v[-1, :, 1] - tr.v[0, :, 1]) / (tr.t[-1] - tr.t[0])
    np.testing.assert_allclose(acc, [a1, a2, a3], atol=1e-9)
    lam = tr.multipliers[:, tr.constraint_labels.index("strings")]
    np.testing.assert_allclose(lam, T, atol=1e-9)
    np.testing.assert_allclose(tr.constraint_forces[:, 0, 1], 2 * T, atol=1e-9)


# --- 5. stability ------------------------------------------------------------------------------


def test_pendulum_hanging_stable_inverted_unstable():
    m, l = 1.3, 0.8
    down = equilibrium(pendulum(0.4, m, l))
    np.testing.assert_allclose(down.x[0], [0.0, -l, 0.0], atol=1e-12)
    assert down.stable is True
    assert down.eigenvalues == pytest.approx([m * G / l], rel=1e-10)  # d²V/ds² = m g / l
    up = equilibrium(pendulum(np.pi - 0.3, m, l))  # a guess near the top
    np.testing.assert_allclose(up.x[0], [0.0, l, 0.0], atol=1e-12)
    assert up.stable is False
    assert up.eigenvalues == pytest.approx([-m * G / l], rel=1e-10)
    # rod force: tension m g at the bottom (λ = −m g), compression m g at the top
    assert down.multipliers[0] == pytest.approx(-m * G) and up.multipliers[0] == pytest.approx(m * G)


def test_bead_on_hoop_with_spring_stability_switch():
    # V(θ) = −m g R cos θ + ½ k |x − top|² = R cos θ (k R − m g) + const (|x − top|² = 2R²(1 + cos θ)),
    # so d²V/ds² at the bottom (s = R θ) is (m g − k R)/R: stable iff k < k_c = m g / R.
    m, R = 0.7, 0.5
    kc = m * G / R
    for k, stable in ((0.98 * kc, True), (1.02 * kc, False), (kc, None)):
        eq = equilibrium(hoop(k, m, R))
        np.testing.assert_allclose(eq.x[0], [0.0, -R, 0.0], atol=1e-12)
        assert eq.stable is stable, k
        assert eq.eigenvalues[0] == pytest.approx((m * G - k * R) / R, abs=1e-9)
    neutral = equilibrium(hoop(kc, m, R))
    assert neutral.soft_modes.shape == (1, 1, 3)
    np.testing.assert_allclose(np.abs(neutral.soft_modes[0, 0]), [1.0, 0.0, 0.0], atol=1e-12)


# --- 6. virtual work at and near equilibria ----------------------------------------------------


def _cases():
    return [
        ("chain", chain(), None),
        ("lever", lever(2.0, 1.0, angle=0.2), None),
        ("pendulum down", pendulum(0.4), None),
        ("pendulum up", pendulum(np.pi - 0.3), None),
        ("hoop stiff", hoop(20.0), None),
    ]


@pytest.mark.parametrize("name, system, guess", _cases(), ids=[c[0] for c in _cases()])
def test_virtual_work_zero_at_equilibrium_not_next_to_it(name, system, guess):
    eq = equilibrium(system, guess)
    assert virtual_work(system, eq.x) < 1e-10
    assert eq.virtual_work_residual < 1e-10
    assert constraint_virtual_work_residual(system, eq.x, eq.multipliers) < 1e-10
    assert virtual_work(system, admissible_step(system, eq)) > 1e-6


def test_generalized_force_of_a_pendulum():
    m, l, th = 1.3, 0.8, 0.7
    s = pendulum(th, m, l)
    dx_dq = np.array([[l * np.cos(th)], [l * np.sin(th)], [0.0]])
    Q = generalized_forces(s, s.positions, dx_dq)
    np.testing.assert_allclose(Q, [-m * G * l * np.sin(th)], rtol=1e-14)
    assert virtual_work(s, s.positions) == pytest.approx(m * G * np.sin(th), rel=1e-12)


def test_redundant_constraints_give_minimum_norm_multipliers():
    # the same rod twice: the load is shared equally, and the result is unchanged
    s = pendulum(0.3)
    s.add(C.Distance("bob", point=[0, 0, 0], length=0.8, name="second rod"))
    eq = equilibrium(s)
    assert eq.multipliers[0] == pytest.approx(eq.multipliers[2], rel=1e-9)
    assert eq.multipliers[0] + eq.multipliers[2] == pytest.approx(-1.3 * G, rel=1e-9)
    assert eq.stable is True


def test_no_equilibrium_raises_input_error_naming_the_residual():
    s = C.System()
    s.add_particle("p", 1.0, [0.0, 0.0, 0.0])
    s.add(C.Plane("p", [0, 0, 1]), C.Gravity([0, -G, 0]))  # slides forever in the plane
    with pytest.raises(C.InputError, match="force balance.*'p' \\(y\\)"):
        equilibrium(s, method="newton")


# --- 7. command line ---------------------------------------------------------------------------


def test_cli_statics_on_hanging_chain(tmp_path, capsys):
    out = tmp_path / "st"
    code = main(["statics", str(ROOT / "scenarios" / "hanging_chain.toml"), "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert (out / "statics.png").stat().st_size > 0
    data = json.loads((out / "equilibrium.json").read_text())
    assert data["converged"] and data["stable"] is True
    assert data["virtual_work_residual"] < 1e-10
    weight = sum(0.5 * G for _ in data["particles"])
    support = sum(r["support_force"][1] for r in data["anchor_reactions"])
    assert support == pytest.approx(weight, abs=1e-8)
    assert "STABLE" in captured.out and "support reactions" in captured.out
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == []


def test_cli_statics_bad_input_exits_2(tmp_path, capsys):
    out = tmp_path / "st"
    code = main(["statics", str(tmp_path / "missing.toml"), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert "Traceback" not in err and err.startswith("constrained: error: ")
    assert len(err.strip().splitlines()) == 1
    bad = tmp_path / "slide.toml"
    bad.write_text(
        '[[particles]]\nname = "p"\nmass = 1.0\nposition = [0.0, 0.0, 0.0]\n\n'
        '[[constraints]]\ntype = "plane"\nparticles = ["p"]\nnormal = [0.0, 0.0, 1.0]\n\n'
        '[[effects]]\ntype = "gravity"\ng = [0.0, -9.81, 0.0]\n'
    )
    code = main(["statics", str(bad), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert "slide.toml" in err and "no static equilibrium" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_ipopt_route_finds_the_minimum():
    eq = equilibrium(pendulum(np.pi - 0.3, 1.3, 0.8), method="ipopt")  # from near the top
    np.testing.assert_allclose(eq.x[0], [0.0, -0.8, 0.0], atol=1e-10)
    assert eq.method == "ipopt" and eq.stable is True and eq.virtual_work_residual < 1e-10


# --- 8. the report: round-off shown as 0, the accuracy said once ---------------------------------


def test_report_prints_zero_below_the_solves_accuracy(tmp_path, capsys):
    """The lever lies in z = 0 with its pivot at the origin: the planes carry no load and the
    z components vanish; the solve leaves them at 1e-15 … 1e-43, which the report shows as 0
    (never "-0"), while the real tensions keep their digits."""
    out = tmp_path / "st"
    assert main(["statics", str(ROOT / "scenarios" / "lever.toml"), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert text.count("accuracy of the solve:") == 1
    lines = text.splitlines()
    block = lines[lines.index(next(ln for ln in lines if ln.startswith("multipliers"))) + 1:]
    planes = [ln for ln in block[:8] if "plane" in ln]
    assert len(planes) == 3 and all(ln.split()[0] == "0" for ln in planes), planes
    assert not re.search(r"(?<![\w.])-0(?![.\d])", text), text   # no "-0"
    assert not re.search(r"e-(1[3-9]|[2-9]\d)\b", text.split("virtual-work residual")[0]), text
    assert "38.1344" in text and "-32.7" in text   # the loads themselves
    data = json.loads((out / "equilibrium.json").read_text())
    assert data["accuracy"]["force_N"] < 1e-8 and data["accuracy"]["position_m"] < 1e-11


def test_report_threshold_follows_each_rows_scale():
    """A surface written as 1e12 · (y + 1) = 0 holds a 1 kg bead with λ = g / 1e12 ≈ 1e-11 per unit
    of f: far below the solve's force accuracy in newtons, and still a real multiplier (λ times
    the row's scale 1e12 is the 9.81 N the surface pushes with), so it is printed, not zeroed."""
    from constrained.analysis.statics_report import accuracy, format_equilibrium

    s = C.System(name="bead on a scaled floor")
    s.add_particle("b", 1.0, [0.3, -1.0, 0.0])
    s.add(C.Surface("b", "1e12 * (y + 1)"), C.Plane("b", [0, 0, 1]), C.Plane("b", [1, 0, 0], 0.3))
    s.add(C.Gravity([0, -G, 0]))
    eq = equilibrium(s)
    lam = eq.multipliers[0]
    assert lam == pytest.approx(G / 1e12, rel=1e-9)  # J = 1e12 ŷ: Jᵀλ is the floor's 9.81 N upward
    np.testing.assert_allclose(eq.constraint_forces[0], [0.0, G, 0.0], atol=1e-9)
    assert abs(lam) < accuracy(eq)[1]
    row = next(ln for ln in format_equilibrium(eq).splitlines() if "1e12" in ln or "1e+12" in ln)
    assert float(row.split()[0]) == pytest.approx(lam, rel=1e-5), row


def test_the_report_shows_round_off_eigenvalues_mode_components_and_energy_as_0():
    """A skate held across a slope by its blade: along a translation in the plane V is
    linear, so the tangent-space Hessian has a zero eigenvalue (a soft mode), and the shape's
    component across the plane, and V with the blade particle at the origin, are 0 — in
    floating point ~1e-15..1e-19. The report must say 0 for them (the accuracy said once),
    and print the other eigenvalues as numbers."""
    import re

    from test_nonholonomic import skate

    from constrained.analysis.statics_report import format_equilibrium

    system, down, side, g_t = skate(heading=1.2)
    eq = C.equilibrium(system)
    text = format_equilibrium(eq)
    eig = next(line for line in text.splitlines() if "tangent-space eigenvalues" in line)
    w2 = next(line for line in text.splitlines() if "squared frequencies" in line)

    def numbers(line):
        return [float(v) for v in re.findall(r"-?\d+(?:\.\d+)?(?:e[-+]?\d+)?",
                                             line.split(":", 1)[1].split("(zero")[0])]

    soft = int(np.sum(np.abs(eq.frequencies_squared) <= eq.stability_tolerance))
    assert soft >= 1
    for line in (eig, w2):
        values = numbers(line)
        assert values.count(0.0) == soft, line          # the neutral directions: exactly "0"
        assert all(v == 0 or abs(v) > 1e-6 for v in values), line  # no round-off printed
    body = text.split("stability:")[1].split("virtual-work residual")[0]  # (residuals are residuals)
    assert not re.search(r"\de-(1\d|[2-9]\d)", body), body  # nothing below 1e-10
    assert "potential energy V = 0 J" in text  # the blade particle at the origin, V = 0 there
