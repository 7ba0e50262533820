"""Hard cases (issue 5): every scene in scenarios/hard/ works, with assertions on drift,
conservation and behaviour. Case 7 (large N) is tested with the sparse KKT work (issue 9);
RATTLE's bounded long-run energy error is tests/test_solvers.py::
test_rattle_long_run_energy_stays_bounded (not repeated here)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

import constrained as C
from constrained.cli.main import main
from constrained.manifold import diagnostics
from constrained.manifold.constraint_report import jacobian_rank
from constrained.manifold.dense import schur_solve
from constrained.manifold.manifold import Manifold
from constrained.run.quantities import multipliers_along
from constrained.run.simulate import consistent_state
from constrained.solvers.stiffness import StiffnessWarning

HARD = Path(__file__).resolve().parent.parent / "scenarios" / "hard"


def scene(name, *overrides):
    return C.load_scene(HARD / f"{name}.toml", list(overrides))


def run(name, t_end=None, **kw):
    sc = scene(name)
    s = sc.settings
    t_end = t_end or s["t_end"]
    dt = s["output_dt"] or t_end / 200
    kw.setdefault("rtol", s["rtol"])
    kw.setdefault("atol", s["atol"])
    kw.setdefault("base", s["base"])
    kw.setdefault("method", s["method"])
    return sc, C.simulate(sc.system, t_end, t_eval=np.arange(0.0, t_end + 1e-9, dt), **kw)


def test_every_hard_scene_has_a_comment_block():
    for path in sorted(HARD.glob("*.toml")):
        text = path.read_text(encoding="utf-8")
        assert text.startswith("#") and "What to look for" in text, path.name
        C.load_scene(path)  # parses


# --- 1. redundant constraints -------------------------------------------------------------------
def _independent_subsystem(system, x, t=0.0):
    """The same system keeping only an independent subset of its constraint rows (one scalar
    row per constraint in these scenes, except planes: kept whole when any row is kept)."""
    model = C.assemble(system)
    rank, order = jacobian_rank(np.asarray(model.jacobian(x, t)[1]))
    keep = set(model.constraint_owner[np.sort(order[:rank])].tolist())
    sub = C.System(name=system.name + " (independent)")
    for p in system.particles:
        sub.add_particle(p.name, p.mass, p.position, p.velocity)
    sub.add(*[c for k, c in enumerate(system.constraints) if k in keep], *system.effects)
    return sub


@pytest.mark.parametrize("name, redundant", [("redundant_cube", 10), ("redundant_plane_triangle", 3),
                                             ("redundant_closed_chain", 1)])
def test_redundant_constraints_give_the_right_net_forces(name, redundant):
    sc, tr = run(name, t_end=1.0)
    report = C.constraint_report(sc.system)
    assert len(report.redundant) == redundant and not report.singular
    assert tr.constraint_residual.max() < 1e-12
    assert np.ptp(tr.energy) < 1e-9 * max(1.0, abs(tr.energy[0]))
    sub = _independent_subsystem(sc.system, sc.system.positions.ravel())
    msub = C.assemble(sub)
    assert C.constraint_report(sub).redundant == []
    scale = max(np.abs(tr.constraint_forces).max(), 1.0)
    for k in range(0, len(tr.t), 10):
        x, v = tr.x[k].ravel(), tr.v[k].ravel()
        _, lam = Manifold(msub).accelerations(x, v, tr.t[k])
        J = np.asarray(msub.jacobian(x, tr.t[k])[1])
        net_sub = (J.T @ lam).reshape(-1, 3)
        assert np.abs(tr.constraint_forces[k] - net_sub).max() < 1e-8 * scale


def test_redundant_cube_keeps_its_angular_momentum():
    _, tr = run("redundant_cube", t_end=1.0)
    L = np.cross(tr.x, tr.v).sum(axis=1)
    assert np.abs(L - L[0]).max() < 1e-8


# --- 2. singular configurations -----------------------------------------------------------------
def test_fourbar_keeps_going_through_its_toggle_positions():
    sc, tr = run("fourbar_toggle")
    assert tr.t[-1] == pytest.approx(2.0)
    assert np.all(np.isfinite(tr.x)) and tr.constraint_residual.max() < 1e-12
    # the rocker reverses (toggle) twice a turn: 4 times in 2 s
    m = C.assemble(sc.system)
    angle = np.unwrap(np.arctan2(tr.x[:, 1, 1], tr.x[:, 1, 0] - 1.0))
    reversals = np.sum(np.diff(np.sign(np.diff(angle))) != 0)
    assert reversals >= 3
    cond = diagnostics.conditioning(m, tr)
    assert np.all(np.isfinite(cond.cond)) and cond.sigma_min.min() > 1e-2
    assert cond.cond.max() < 1e3


def test_fourbar_past_its_limit_stops_naming_the_constraints(tmp_path, capsys):
    sc = scene("fourbar_limit")
    with pytest.raises(C.SimulationError) as err:
        C.simulate(sc.system, 3.0, rtol=1e-10, atol=1e-12, t_eval=np.arange(0, 3.0, 0.005))
    msg = str(err.value)
    assert "singular configuration" in msg and "'coupler BC'" in msg and "'rocker DC'" in msg
    partial = err.value.trajectory
    assert partial is not None and 1.0 < partial.t[-1] < 1.3
    assert np.all(np.isfinite(partial.x))
    cond = diagnostics.conditioning(C.assemble(sc.system), partial)
    assert cond.sigma_min[-1] < 0.1 < cond.sigma_min[0]  # approaching the rank drop
    assert main(["run", str(HARD / "fourbar_limit.toml"), "--out", str(tmp_path), "--quiet"]) == 1
    assert "'coupler BC'" in capsys.readouterr().err
    assert (tmp_path / "trajectory.npz").exists()


def test_slider_crank_passes_dead_centre():
    sc, tr = run("slider_crank_dead_centre", t_end=3.0)
    assert tr.constraint_residual.max() < 1e-12
    assert np.ptp(tr.energy) < 1e-9 * tr.energy[0]
    crank = np.unwrap(np.arctan2(tr.x[:, 0, 1], tr.x[:, 0, 0]))
    assert crank[-1] - crank[0] > 3 * np.pi  # a dead centre every half turn: at least three
    cond = diagnostics.conditioning(C.assemble(sc.system), tr)
    assert np.isfinite(cond.cond).all() and cond.sigma_min.min() > 0.1


def test_chain_released_stretched_whips_without_trouble():
    sc, tr = run("stretched_chain")
    assert np.all(np.isfinite(tr.x)) and np.all(np.isfinite(tr.multipliers))
    assert tr.constraint_residual.max() < 1e-12
    assert np.ptp(tr.energy) < 1e-8 * 50
    assert np.abs(tr.multipliers[0]).max() < 1e-9  # collinear at rest: no tension at t = 0
    speed = np.linalg.norm(tr.v[:, -1], axis=1)
    assert speed.max() > 5.0  # the whip


# --- 3. stiffness -------------------------------------------------------------------------------
def test_stiff_axle_implicit_base_takes_few_steps():
    sc, tr = run("stiff_axle", t_end=1.0)
    assert tr.constraint_residual.max() < 1e-12
    assert tr.stats["steps"] < 4000
    road = 0.02 * np.sin(2 * 10 * tr.t) + 0.01 * np.sin(7 * 10 * tr.t)
    assert np.abs(tr.x[:, 0, 1] - road - 0.3).max() < 1e-3
    assert "stiffness" not in tr.stats  # no warning machinery on implicit bases


def test_stiff_axle_explicit_base_is_warned_about():
    sc = scene("stiff_axle")
    with pytest.warns(StiffnessWarning, match="Radau"):
        tr = C.simulate(sc.system, 0.15, base="DOP853", rtol=1e-6, atol=1e-8)
    assert tr.stats["stiffness"]["stiff"] and tr.stats["stiffness"]["rho_max"] > 5e3


def test_smooth_scene_is_not_called_stiff():
    with warnings.catch_warnings():
        warnings.simplefilter("error", StiffnessWarning)
        _, tr = run("slider_crank_dead_centre", t_end=3.0)
    assert not tr.stats["stiffness"]["stiff"]


# --- 4. chaos and long runs ---------------------------------------------------------------------
def test_double_pendulum_1000_s_keeps_its_constraints():
    sc = scene("double_pendulum_1000s")
    tr = C.simulate(sc.system, 1000.0, method="projection", base="CVODES", rtol=1e-10, atol=1e-12,
                    t_eval=np.linspace(0, 1000, 2001), outputs={"energy", "constraint_residual",
                                                               "velocity_residual"})
    assert tr.t[-1] == 1000.0
    assert tr.constraint_residual.max() <= 1e-10
    assert tr.velocity_residual.max() <= 1e-10
    assert np.abs(tr.energy - tr.energy[0]).max() < 1e-4


# --- 5. fast rheonomic drive --------------------------------------------------------------------
@pytest.mark.parametrize("nu, stays_up", [(90.0, True), (50.0, False)])
def test_kapitza_threshold(nu, stays_up):
    a, l, g = 0.02, 0.1, 9.81
    assert (a**2 * nu**2 > 2 * g * l) == stays_up
    sc = scene("kapitza_threshold", f"parameters.nu={nu}")
    tr = C.simulate(sc.system, 1.0, rtol=1e-9, atol=1e-11, t_eval=np.arange(0, 1.0, 0.002))
    cos_top = (tr.x[:, 0, 1] - a * np.cos(nu * tr.t)) / l
    assert tr.constraint_residual.max() < 1e-12
    if stays_up:
        assert cos_top.min() > 0.9
    else:
        assert cos_top.min() < 0.0  # it fell below the pivot's level


@pytest.mark.parametrize("w", [4.0, 2.0])
def test_damped_bead_settles_at_the_predicted_angle(w):
    g, R = 9.81, 1.0
    expected = np.arccos(g / (w**2 * R)) if w**2 > g / R else 0.0
    sc = scene("bead_hoop_damped", f"parameters.w={w}")
    v = sc.system.particles[0].velocity
    sc.system.particles[0].velocity = np.array([0.0, w * np.sin(0.5), 0.0]) if np.any(v) else v
    tr = C.simulate(sc.system, 40.0, rtol=1e-9, atol=1e-11, t_eval=np.linspace(0, 40, 81),
                    outputs={"constraint_residual"})
    theta = np.arccos(np.clip(-tr.x[:, 0, 2], -1, 1))
    assert abs(theta[-1] - expected) < 1e-3
    assert tr.constraint_residual.max() < 1e-12


# --- 6. extreme mass ratios ---------------------------------------------------------------------
def test_extreme_mass_ratio_agrees_with_the_two_body_limit():
    from scipy.integrate import solve_ivp

    sc, tr = run("extreme_mass_ratio", t_end=2.0)
    g, L1, L2, M, m, th0 = 9.81, 1.0, 0.5, 1e6, 1e-6, 0.5
    assert tr.constraint_residual.max() < 1e-12
    # heavy bob: the simple pendulum, unaffected by the light particle
    ref = solve_ivp(lambda t, y: [y[1], -g / L1 * np.sin(y[0])], (0, 2.0), [th0, 0.0],
                    t_eval=tr.t, rtol=1e-12, atol=1e-12, dense_output=True)
    th = ref.y[0]
    H = np.stack([L1 * np.sin(th), -L1 * np.cos(th)], axis=1)
    assert np.abs(tr.x[:, 0, :2] - H).max() < 1e-7

    # light particle: a pendulum on the moving pivot H(t)
    def pivot_acc(t):
        q, w = ref.sol(t)
        alpha = -g / L1 * np.sin(q)
        return L1 * np.array([alpha * np.cos(q) - w**2 * np.sin(q), alpha * np.sin(q) + w**2 * np.cos(q)])

    def light(t, y):  # phi from the downward vertical
        ax, ay = pivot_acc(t)
        return [y[1], (-(g + ay) * np.sin(y[0]) - ax * np.cos(y[0])) / L2]

    phi = solve_ivp(light, (0, 2.0), [0.0, 0.0], t_eval=tr.t, rtol=1e-12, atol=1e-12).y[0]
    rel = tr.x[:, 1, :2] - tr.x[:, 0, :2]
    assert np.abs(np.arctan2(rel[:, 0], -rel[:, 1]) - phi).max() < 1e-6
    # tensions at t = 0 (closed form) from the scaled multiplier solve
    lam = multipliers_along(C.assemble(sc.system), tr.x, tr.v, tr.t)
    assert abs(lam[0, 0]) == pytest.approx(M * g * np.cos(th0), rel=1e-9)
    assert abs(lam[0, 1]) == pytest.approx(m * g * np.cos(th0) ** 2, rel=1e-6)
    # and along the run the light thread's tension is m |a_l - g|
    model = C.assemble(sc.system)
    acc = np.array([Manifold(model).accelerations(x.ravel(), v.ravel(), t)[0][3:5]
                    for x, v, t in zip(tr.x, tr.v, tr.t, strict=True)])
    need = m * np.linalg.norm(acc - np.array([0, -g]), axis=1)
    assert np.abs(np.abs(lam[:, 1]) - need).max() < 1e-6 * need.max()


def test_scaled_schur_solve_keeps_the_heavy_row():
    sc = scene("extreme_mass_ratio")
    model = C.assemble(sc.system)
    x, v = sc.system.positions.ravel(), np.zeros(6)
    F, J, gamma = (np.asarray(a) for a in model.dynamics(x, v, 0.0))
    b = -gamma.ravel() - J @ (model.inverse_masses * F.ravel())
    lam = schur_solve(J, model.inverse_masses, b)
    _, lam_fast = Manifold(model).accelerations(x, v, 0.0)  # CasADi's sparse LDLᵀ path
    assert lam == pytest.approx(lam_fast, rel=1e-9)


# --- 8. inconsistent starts ---------------------------------------------------------------------
def test_small_inconsistency_is_projected_and_reported():
    sc = scene("fourbar_toggle")
    system = sc.system
    system.particles[1].position = system.particles[1].position + np.array([1e-4, -1e-4, 0.0])
    tr = C.simulate(system, 0.05, rtol=1e-10, atol=1e-12)
    corr = tr.info["initial_correction"]
    assert 5e-5 < corr["position"] < 2e-4 and corr["worst_constraint"] in ("coupler BC", "rocker DC")
    assert tr.constraint_residual.max() < 1e-12


def test_large_inconsistency_is_refused_naming_the_worst_constraint():
    sc = scene("fourbar_toggle")
    sc.system.particles[1].position = sc.system.particles[1].position + np.array([0.0, 0.5, 0.0])
    with pytest.raises(C.InconsistentStateError, match="rocker DC"):
        C.simulate(sc.system, 0.05)


def test_impossible_triangle_is_refused_by_check_naming_the_constraints(capsys):
    assert main(["check", str(HARD / "impossible_triangle.toml")]) == 2
    err = capsys.readouterr().err
    for name in ("side ab", "side bc", "side ca"):
        assert f"'{name}'" in err
    model = C.assemble(scene("impossible_triangle").system)
    clash = diagnostics.incompatible_constraints(model)
    assert not clash.compatible and sorted(clash.labels) == ["side ab", "side bc", "side ca"]
    assert clash.residual == pytest.approx(1 / 3, rel=1e-6)  # 3 - (1 + 1) shared by three sides
    with pytest.raises(C.InconsistentStateError, match="side ab"):
        consistent_state(model, model.system.positions, model.system.velocities)


# --- 9. blow-up -------------------------------------------------------------------------------
def test_blow_up_stops_with_time_state_cause_and_saves(tmp_path, capsys):
    sc = scene("blowup_attractive")
    t_star = np.pi / 2 * np.sqrt(1 / 2)
    with pytest.raises(C.SimulationError) as err:
        C.simulate(sc.system, 2.0, rtol=1e-10, atol=1e-12, t_eval=np.arange(0, 2.0, 0.01))
    msg = str(err.value)
    assert "likely cause: forces that blow up" in msg and "particle 'p'" in msg
    assert f"t = {t_star:.5f}"[:-1] in msg  # t = 1.1107
    partial = err.value.trajectory
    assert partial.t[-1] == pytest.approx(t_star, abs=0.011) and np.all(np.isfinite(partial.x))
    assert main(["run", str(HARD / "blowup_attractive.toml"), "--out", str(tmp_path), "--quiet"]) == 1
    assert "saved in" in capsys.readouterr().err
    saved = C.Trajectory.load(tmp_path / "trajectory.npz")
    assert saved.t[-1] == pytest.approx(partial.t[-1])


# --- the [expect] checks of every scene that runs to its end ------------------------------------
@pytest.mark.parametrize("name", ["redundant_plane_triangle", "redundant_closed_chain", "fourbar_toggle",
                                  "stretched_chain", "stiff_axle", "extreme_mass_ratio"])
def test_hard_scene_expect_checks_pass(name, tmp_path, capsys):
    code = main(["run", str(HARD / f"{name}.toml"), "--quiet", "--out", str(tmp_path)])
    assert code == 0, capsys.readouterr()


def test_stiff_axle_is_warned_about_by_dopri_too():
    sc = scene("stiff_axle")
    with pytest.warns(StiffnessWarning, match="dopri's explicit DOP853.*Radau"):
        tr = C.simulate(sc.system, 0.15, method="dopri", rtol=1e-6, atol=1e-8, compiled=False)
    assert tr.stats["stiffness"]["stiff"] and tr.stats["stiffness"]["rho_max"] > 5e3
    with warnings.catch_warnings():
        warnings.simplefilter("error", StiffnessWarning)
        _, smooth = run("slider_crank_dead_centre", t_end=3.0, method="dopri", compiled=False)
    assert not smooth.stats["stiffness"]["stiff"]


def test_dopri_past_the_fourbar_limit_stops_naming_the_constraints():
    sc = scene("fourbar_limit")
    with pytest.raises(C.SimulationError) as err:
        C.simulate(sc.system, 3.0, method="dopri", rtol=1e-10, atol=1e-12,
                   t_eval=np.arange(0, 3.0, 0.005), compiled=False)
    msg = str(err.value)
    assert "singular configuration" in msg and "'coupler BC'" in msg and "'rocker DC'" in msg
    partial = err.value.trajectory
    assert 1.0 < partial.t[-1] < 1.3 and np.all(np.isfinite(partial.x))
