"""Normal modes and the reduced route on scenes nobody here chose (session 15).

Expected values are derived here: the discrete hanging string's tridiagonal eigenproblem (point
masses, massless links: link j carries the weight below it), the continuous chain's
ω_k = (j_{0,k}/2)√(g/L), the linearized triple pendulum's M and K, the inverted double
pendulum's growth rates; a free body's six zero modes counted exactly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.linalg as sla
from scipy.special import jn_zeros

import constrained as C
from constrained.cli.main import main

ROOT = Path(__file__).resolve().parents[1]
G = 9.81


def chain(masses, link=0.01, *, g=-G, redundant=False) -> C.System:
    """Beads hanging straight down from a pin at the origin on rods of ``link`` metres, planar."""
    s = C.System(name="chain")
    for i, m in enumerate(masses):
        s.add_particle(f"p{i}", float(m), [0.0, -(i + 1) * link, 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=link))
    for i in range(1, len(masses)):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=link))
        if redundant:
            s.add(C.Distance(f"p{i}", f"p{i - 1}", length=link))
    s.add(C.Gravity([0, g, 0]), C.Plane(s.names, [0, 0, 1]))
    return s


def string_omega2(masses, link=0.01) -> np.ndarray:
    """m_j ü_j = τ_{j+1}(u_{j+1} − u_j)/l − τ_j(u_j − u_{j−1})/l, τ_j = g Σ_{i≥j} m_i, u_{−1} = 0."""
    m = np.asarray(masses, float)
    k = G * np.cumsum(m[::-1])[::-1] / link
    K = np.diag(k + np.append(k[1:], 0.0)) - np.diag(k[1:], 1) - np.diag(k[1:], -1)
    return sla.eigh(K, np.diag(m), eigvals_only=True)


def test_a_fine_chain_by_the_sparse_route_is_the_discrete_string_and_nears_bessel():
    n = 150  # 300 rows: the large model's sparse route
    masses = np.full(n, 0.001)
    s = chain(masses)
    modes = C.modes(s, x=s.positions, count=6)
    assert modes.partial and len(modes.modes) == 6 and modes.degrees_of_freedom == n
    assert modes.stable is True and "the lowest 6" in modes.table()
    np.testing.assert_allclose(modes.frequencies ** 2, string_omega2(masses)[:6], rtol=1e-9)
    continuous = jn_zeros(0, 3) / 2 * np.sqrt(G / (n * 0.01))
    np.testing.assert_allclose(modes.frequencies[:3], continuous, rtol=3e-3)  # discretization: O(1/n)
    # the shapes keep every rod's length to first order: (x_i − x_{i−1})·(φ_i − φ_{i−1}) = 0
    x = np.vstack([np.zeros(3), s.positions])
    for shape in modes.shapes.real:
        phi = np.vstack([np.zeros(3), shape])
        assert np.max(np.abs(np.sum(np.diff(x, axis=0) * np.diff(phi, axis=0), axis=1))) < 1e-12
    B = modes.basis  # mass-orthonormal: Φᵀ M Φ = I
    np.testing.assert_allclose(B.T @ (np.repeat(masses, 3)[:, None] * B), np.eye(6), atol=1e-10)


def test_an_upside_down_chain_reports_its_most_negative_omega2_first_by_the_sparse_route():
    # gravity reversed: the rods are in compression and the tangent stiffness is −(the hanging one's)
    n = 60
    masses = np.full(n, 0.002)
    s = chain(masses, g=G)
    modes = C.modes(s, x=s.positions, count=3)
    assert modes.stable is False and "UNSTABLE (at least 3" in modes.stability
    w2 = modes.frequencies ** 2 - np.array([m.growth_rate for m in modes.modes]) ** 2
    np.testing.assert_allclose(np.sort(w2), -string_omega2(masses)[::-1][:3], rtol=1e-9)


def test_one_tonne_among_grams_is_the_string_with_a_heavy_end():
    masses = [0.001] * 9 + [1000.0]
    modes = C.modes(chain(masses))
    w2 = string_omega2(masses)
    # ω² spans 98 to 3.8e9 /s²: a symmetric eigensolver's error is ~ε‖K‖ absolute (8.7e-9 of the lowest)
    np.testing.assert_allclose(modes.frequencies ** 2, w2, rtol=1e-9, atol=1e-15 * w2[-1])
    # the heavy end swings as a simple pendulum of the chain's length
    np.testing.assert_allclose(modes.frequencies[0], np.sqrt(G / 0.1), rtol=1e-5)


def test_redundant_rods_change_no_frequency_dense_or_sparse():
    masses = np.linspace(0.001, 0.003, 8)
    modes = C.modes(chain(masses, redundant=True))
    assert modes.degrees_of_freedom == 8
    np.testing.assert_allclose(modes.frequencies ** 2, string_omega2(masses), rtol=1e-9)
    big = np.full(40, 0.001)  # 40 + 39 + 40 rows > 100: the sparse route holds the repeats out
    s = chain(big, redundant=True)
    sparse = C.modes(s, x=s.positions, count=4)
    assert sparse.degrees_of_freedom == 40
    np.testing.assert_allclose(sparse.frequencies ** 2, string_omega2(big)[:4], rtol=1e-9)


def test_a_free_rigid_body_has_exactly_six_zero_modes():
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1.0]]) * 0.3
    s = C.System(name="body")
    for i, p in enumerate(pts):
        s.add_particle(f"b{i}", 0.001 * (i + 1), p)
    for i in range(5):
        for j in range(i + 1, 5):
            s.add(C.Distance(f"b{i}", f"b{j}", length=float(np.linalg.norm(pts[i] - pts[j]))))
    modes = C.modes(s, x=pts)
    assert modes.degrees_of_freedom == 6 and [m.kind for m in modes.modes] == ["soft"] * 6
    assert modes.stable is None and "6 soft" in modes.stability


def test_the_inverted_double_pendulum_grows_at_the_closed_form_rates():
    s = C.System(name="inverted")
    s.add_particle("p1", 1.0, [0, 1, 0])
    s.add_particle("p2", 1.0, [0, 2, 0])
    s.add(C.Distance("p1", point=[0, 0, 0], length=1.0), C.Distance("p1", "p2", length=1.0),
          C.Gravity([0, -G, 0]), C.Plane(["p1", "p2"], [0, 0, 1]))
    modes = C.modes(s, x=s.positions)
    assert modes.stable is False and "UNSTABLE (2 growing" in modes.stability
    assert [m.kind for m in modes.modes] == ["divergent"] * 2
    np.testing.assert_allclose(sorted(m.growth_rate for m in modes.modes),
                               np.sqrt(G * np.array([2 - np.sqrt(2), 2 + np.sqrt(2)])), rtol=1e-10)


def test_a_start_off_equilibrium_is_refused_and_left_out_statics_finds_the_rest():
    s = C.System(name="pendulum")
    s.add_particle("bob", 0.01, [0.5, -np.sqrt(0.75), 0])
    s.add(C.Distance("bob", point=[0, 0, 0], length=1.0), C.Gravity([0, -G, 0]), C.Plane(["bob"], [0, 0, 1]))
    with pytest.raises(C.InputError, match=r"not at rest.*tangential acceleration of 4\.2"):
        C.modes(s, x=s.positions)  # 30° from the vertical: g sin 30° cos 30° = 4.248 m/s² along x
    np.testing.assert_allclose(C.modes(s).frequencies, [np.sqrt(G)], rtol=1e-10)


def test_every_mode_of_a_huge_model_is_refused_naming_count():
    n = 1250  # 3N + C = 3,750 + 2,500 > 6,000: refused before any matrix is formed
    s = chain(np.full(n, 0.001))
    with pytest.raises(C.InputError, match="count"):
        C.modes(s, x=s.positions)


def triple(t_end: float, start: str, tmp_path: Path) -> Path:
    bobs = ", ".join(f'p{i + 1} = ["{"+".join(f"sin({c})" for c in "abc"[:i + 1])}", '
                     f'"{"".join(f"-cos({c})" for c in "abc"[:i + 1])}", "0"]' for i in range(3))
    text = TRIPLE.replace("MAP", "{ " + bobs + " }")
    path = tmp_path / "triple.toml"
    path.write_text(text.replace("T_END", str(t_end)).replace("START", start))
    return path


TRIPLE = """
[scene]
name = "triple pendulum 1 kg / 1 g / 1 kg"
[[particles]]
name = "p1"
mass = 1.0
position = [0, -1, 0]
[[particles]]
name = "p2"
mass = 0.001
position = [0, -2, 0]
[[particles]]
name = "p3"
mass = 1.0
position = [0, -3, 0]
[[constraints]]
type = "distance"
a = "p1"
point = [0, 0, 0]
length = 1.0
[[constraints]]
type = "distance"
a = "p1"
b = "p2"
length = 1.0
[[constraints]]
type = "distance"
a = "p2"
b = "p3"
length = 1.0
[[constraints]]
type = "plane"
particles = ["p1", "p2", "p3"]
normal = [0, 0, 1]
[[effects]]
type = "gravity"
g = [0, -9.81, 0]
[simulate]
t_end = T_END
rtol = 1e-10
atol = 1e-12
[reduced]
coordinates = ["a", "b", "c"]
initial = START
rates = { a = 0, b = 0, c = 0 }
map = MAP
"""


def test_triple_pendulum_kilogram_gram_kilogram_modes_and_runs_agree(tmp_path):
    scene = C.load_scene(triple(1.0, "{ a = 0.4, b = -0.3, c = 0.2 }", tmp_path))
    m = np.array([1.0, 0.001, 1.0])
    # linearized Lagrange, unit rods: M_ij = Σ_{k≥max(i,j)} m_k, K = g diag(tail)
    tail = np.cumsum(m[::-1])[::-1]
    M = np.array([[tail[max(i, j)] for j in range(3)] for i in range(3)])
    modes = C.modes(scene.system)
    np.testing.assert_allclose(modes.frequencies ** 2, sla.eigh(G * np.diag(tail), M, eigvals_only=True),
                               rtol=1e-9)
    assert modes.cross_check(C.ReducedModel.from_scene(scene)).difference < 1e-10
    check = C.cross_check(scene)
    assert check.max_position_difference < 1e-7 and check.max_energy_difference < 1e-7
    assert check.horizon()[0] is None and "whole run" in check.horizon_line()


def test_a_chaotic_run_says_when_the_routes_separate_and_the_energies_still_agree(tmp_path):
    scene = C.load_scene(triple(8.0, "{ a = 2.0, b = 2.5, c = 1.0 }", tmp_path))
    check = C.cross_check(scene, rtol=1e-8, atol=1e-10)
    t_sep, tau = check.horizon()
    assert t_sep is not None and 0 < t_sep < 8.0 and tau is not None and 0 < tau < t_sep
    assert check.max_position_difference > 1e-2  # the positions really separated
    assert check.max_energy_difference < 1e-5  # the energy both routes conserve did not
    assert "routes separate" in check.table() and "Lyapunov" in check.table()


def pole_scene(tmp_path: Path, th: float, rate: str) -> Path:
    text = (ROOT / "scenarios" / "spherical_pendulum.toml").read_text()
    text = text.split("[expect]")[0] + "[reduced]" + text.split("[reduced]")[1]
    text = text.replace("initial = { th = 0.6, ph = 0.0 }", f"initial = {{ th = {th}, ph = 0.0 }}")
    text = text.replace("rates = { th = 0.0, ph = 2.5 }", f"rates = {rate}")
    text = text.replace("t_end = 10.0", "t_end = 1.0")
    path = tmp_path / "pole.toml"
    path.write_text(text)
    return path


def test_the_reduced_route_at_the_pole_of_its_angles_says_so_instead_of_hanging(tmp_path, capsys):
    path = pole_scene(tmp_path, 0.0, "{ th = 0.0, ph = 2.0 }")
    with pytest.raises(C.InputError, match=r"singular there \(rank ∂x/∂q = 1 < 2"):
        C.cross_check(C.load_scene(path))
    assert main(["crosscheck", str(path), "--out", str(tmp_path / "o")]) == 2
    assert "pole of spherical angles" in capsys.readouterr().err
    # a swing through the pole (th' ≠ 0, ph' = 0) never lands on it: the routes agree
    through = C.cross_check(C.load_scene(pole_scene(tmp_path, 0.3, "{ th = -2.0, ph = 0.0 }")))
    assert through.max_position_difference < 1e-8


def test_modes_at_the_pole_do_not_compare_the_singular_reduced_route(tmp_path, capsys):
    scene = C.load_scene(ROOT / "scenarios" / "spherical_pendulum.toml")
    modes = C.modes(scene.system)  # hanging straight down: th = 0, the pole of the angles
    np.testing.assert_allclose(modes.frequencies, [np.sqrt(G)] * 2, rtol=1e-10)
    with pytest.raises(C.InputError, match="singular at this state"):
        modes.cross_check(C.ReducedModel.from_scene(scene))
    assert main(["modes", str(ROOT / "scenarios" / "spherical_pendulum.toml"), "--out", str(tmp_path / "m"),
                 "--no-animation"]) == 0
    out = capsys.readouterr().out
    assert "not compared" in out and "DISAGREE" not in out


def test_cli_count_and_bad_count(tmp_path, capsys):
    assert main(["modes", str(ROOT / "scenarios" / "double_pendulum.toml"), "--count", "0",
                 "--out", str(tmp_path / "a")]) == 2
    assert main(["modes", str(ROOT / "scenarios" / "hanging_chain.toml"), "--count", "2",
                 "--out", str(tmp_path / "b"), "--no-animation"]) == 0
    assert "the lowest 2 mode(s)" in capsys.readouterr().out


def _double_pendulum_without_tolerances(tmp_path):
    import re

    from conftest import SCENARIOS

    text = (SCENARIOS / "double_pendulum.toml").read_text()
    path = tmp_path / "dp.toml"
    path.write_text(re.sub(r"^(rtol|atol) = .*\n", "", text, flags=re.M))
    return path


def test_crosscheck_uses_its_tighter_default_unless_the_scene_or_caller_gives_tolerances(tmp_path, capsys):
    """A scene without rtol/atol is cross-checked at 1e-10 (not simulate's 1e-8), and both routes
    then agree to far better than 1e-8 would give: the integrators' error is about the tolerance
    times the motion's size (1 m) over 1 s, 2e-8 m at 1e-8, 2e-10 m at 1e-10."""
    from conftest import SCENARIOS

    from constrained.analysis.crosscheck import cross_check
    from constrained.cli.main import main

    path = _double_pendulum_without_tolerances(tmp_path)
    scene = C.load_scene(path)
    assert scene.settings["rtol"] == 1e-8 and "rtol" not in scene.given_settings  # settings unchanged
    check = cross_check(scene, 1.0)
    assert check.settings["rtol"] == 1e-10 and check.settings["atol"] == 1e-10
    assert check.max_position_difference < 2e-9  # 1e-8 gives about 2e-8 m here
    loose = cross_check(scene, 1.0, rtol=1e-8, atol=1e-8)  # the caller's choice wins
    assert loose.settings["rtol"] == 1e-8 and loose.max_position_difference > 2e-9
    given = C.load_scene(SCENARIOS / "bead_on_rotating_hoop.toml")  # gives rtol 1e-10, atol 1e-12
    assert cross_check(given, 0.5).settings["atol"] == 1e-12
    assert main(["crosscheck", str(path), "--set", "simulate.t_end=0.5", "--out", str(tmp_path / "a")]) == 0
    assert "rtol 1e-10" in capsys.readouterr().out
    assert main(["crosscheck", str(path), "--set", "simulate.t_end=0.5", "--set", "simulate.rtol=1e-7",
                 "--out", str(tmp_path / "b")]) == 0
    assert "rtol 1e-07" in capsys.readouterr().out
