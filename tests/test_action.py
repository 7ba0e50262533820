"""The principle of least action: the action of a run, its stationarity, boundary-value paths."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import double_pendulum, planar_pendulum
from scipy.integrate import solve_ivp

import constrained as C
from constrained.analysis.action import action, end_configuration, stationarity, stationary_path
from constrained.cli.main import main
from constrained.model.structure import assemble

G = 9.81


def bob(theta: float) -> list[float]:
    return [np.sin(theta), -np.cos(theta), 0.0]


# --- straight lines and parabolas: exact at the nodes -----------------------------------------


@pytest.mark.parametrize("quadrature", ["midpoint", "trapezoid"])
def test_free_particle_path_is_the_straight_line(quadrature):
    s = C.System(name="free")
    s.add_particle("a", 2.0, [0.0, 0.0, 0.0])
    x0, x1, T = np.array([0.0, 0.0, 0.0]), np.array([1.0, -2.0, 0.5]), 1.5
    errors = []
    for K in (4, 16, 64):
        t = np.linspace(0, T, K + 1)
        wiggle = x0 + np.outer(t / T, x1 - x0) + 0.3 * np.sin(np.pi * t / T)[:, None]  # a bent start path
        r = stationary_path(s, x0, x1, T, nodes=K, quadrature=quadrature, guess=wiggle[:, None, :])
        assert r.converged and r.iterations >= 1
        exact = x0 + np.outer(r.t / T, x1 - x0)
        errors.append(max(np.abs(r.x[:, 0] - exact).max(), np.abs(r.v[:, 0] - (x1 - x0) / T).max()))
        assert r.action == pytest.approx(0.5 * 2.0 * np.sum((x1 - x0) ** 2) / T, rel=1e-12)
        # lowest mode of m (x_{k+1} − 2x_k + x_{k−1}) / h²: m (2/h)² sin²(π/2K) → m π²/T²
        lowest = 2.0 * (2 * K / T * np.sin(np.pi / (2 * K))) ** 2
        assert r.is_minimum and r.second_variation == pytest.approx(lowest)
    # the discrete Euler–Lagrange equations are x_{k+1} − 2 x_k + x_{k−1} = 0: exact at every K
    assert max(errors) < 1e-8, errors


@pytest.mark.parametrize("quadrature", ["midpoint", "trapezoid"])
@pytest.mark.parametrize("method", ["stationary", "minimize"])
def test_particle_in_gravity_path_is_the_parabola(quadrature, method):
    s = C.System(name="thrown")
    s.add_particle("a", 1.0, [0.0, 0.0, 0.0])
    s.add(C.Gravity([0.0, -G, 0.0]))
    g = np.array([0.0, -G, 0.0])
    x1, T = np.array([2.0, 1.0, 0.5]), 1.2
    v0 = (x1 - 0.5 * g * T**2) / T
    errors = {}
    for K in (3, 12, 48):
        r = stationary_path(s, [0, 0, 0], x1, T, nodes=K, quadrature=quadrature, method=method)
        assert r.converged
        tt = r.t[:, None]
        errors[K] = max(np.abs(r.x[:, 0] - (v0 * tt + 0.5 * g * tt**2)).max(),
                        np.abs(r.v[:, 0] - (v0 + g * tt)).max())
    # second difference of a parabola = h² g exactly: no discretization error at the nodes
    assert max(errors.values()) < 1e-8, errors


# --- the pendulum: initial-value agreement, convergence order, conjugate point -----------------


def test_pendulum_path_agrees_with_the_initial_value_solution():
    s = planar_pendulum(0.3)
    T = 0.8  # shorter than half a period π √(l/g) ≈ 1.003 s
    paths = {K: stationary_path(s, bob(0.3), bob(-0.2), T, nodes=K) for K in (50, 100, 200)}
    for r in paths.values():
        assert r.converged and r.is_minimum
        assert np.max(r.trajectory.constraint_residual) < 1e-10
    # convergence order in the node count: the node error against the motion from the
    # extrapolated start is O(h²)
    a, b = paths[100], paths[200]
    x_r = (4 * b.x[::2] - a.x) / 3  # Richardson: O(h⁴)
    v_r = (4 * b.v[::2] - a.v) / 3
    ivp = C.simulate(s.with_state(x_r[0], v_r[0]), T, rtol=1e-12, atol=1e-12, t_eval=a.t)
    assert np.abs(ivp.x - x_r).max() < 1e-6
    assert np.abs(ivp.v - v_r).max() < 1e-5
    ref = C.simulate(s.with_state(x_r[0], v_r[0]), T, rtol=1e-12, atol=1e-12, t_eval=paths[50].t)
    err = {K: np.abs(ref.x - r.x[:: K // 50]).max() for K, r in paths.items()}
    orders = [np.log2(err[50] / err[100]), np.log2(err[100] / err[200])]
    assert all(1.8 < p < 2.2 for p in orders), (err, orders)
    # the single-grid path at 200 intervals agrees with its own initial-value run to O(h²)
    own = C.simulate(s.with_state(b.x[0], b.v[0]), T, rtol=1e-12, atol=1e-12, t_eval=b.t)
    assert np.abs(own.x - b.x).max() < 1e-5
    # multipliers and constraint forces come with the path: rod tension ≈ m g cos θ + m l θ'²
    assert b.trajectory.multipliers.shape == (len(b.t), 2)
    assert b.trajectory.constraint_forces.shape == (len(b.t), 1, 3)
    assert np.abs(b.trajectory.constraint_forces - own.constraint_forces).max() < 1e-3


def test_pendulum_beyond_the_conjugate_point_is_a_saddle():
    s = planar_pendulum(0.1)
    short = stationary_path(s, bob(0.1), bob(0.05), 0.8, nodes=100)
    long = stationary_path(s, bob(0.1), bob(0.05), 1.5, nodes=100)  # > π √(l/g) ≈ 1.003 s
    assert short.is_minimum and short.second_variation > 0
    assert long.converged
    assert not long.is_minimum and long.second_variation <= 0
    # small oscillations: min δ²S / ∫|η|² dt ≈ m ((π/T)² − g/l)
    assert long.second_variation == pytest.approx(np.pi**2 / 1.5**2 - G, rel=0.05)
    # the saddle is a true motion: the initial-value run from its start reproduces it
    ivp = C.simulate(s.with_state(long.x[0], long.v[0]), 1.5, rtol=1e-12, atol=1e-12, t_eval=long.t)
    assert np.abs(ivp.x - long.x).max() < 1e-3
    # minimizing instead leaves the saddle for another path of lower action
    low = stationary_path(s, bob(0.1), bob(0.05), 1.5, nodes=100, method="minimize")
    assert low.is_minimum and low.action < long.action


def test_trapezoid_path_reproduces_rattle():
    """RATTLE is the forward recursion of the trapezoid discrete Euler–Lagrange equations:
    the boundary-value path through a RATTLE run's end points is that run, velocities too."""
    s = double_pendulum(0.5, 0.8)
    h, K = 0.01, 80
    run = C.simulate(s, h * K, method="rattle", dt=h, t_eval=np.linspace(0, h * K, K + 1))
    path = stationary_path(s, run.x[0], run.x[-1], h * K, nodes=K, quadrature="trapezoid")
    assert np.abs(path.x - run.x).max() < 1e-9
    assert np.abs(path.v - run.v).max() < 1e-8


# --- the action of a run and its stationarity ----------------------------------------------


def test_action_of_uniform_motion_and_history():
    s = C.System(name="free")
    s.add_particle("a", 3.0, [0.0, 0.0, 0.0], [1.0, 2.0, 0.0])
    t = np.linspace(0.0, 2.0, 11)
    x = (t[:, None] * np.array([1.0, 2.0, 0.0]))[:, None, :]
    res = action(s, C.Trajectory(t=t, x=x, v=np.broadcast_to([[1.0, 2.0, 0.0]], x.shape).copy()))
    assert res.total == pytest.approx(0.5 * 3.0 * 5.0 * 2.0)
    assert np.allclose(res.cumulative, 7.5 * t)
    assert res.excluded == []


def misprinted_double_pendulum(th1: float, th2: float, t: np.ndarray) -> C.Trajectory:
    """The motion of the theory text's printed (wrong) double-pendulum equations, m = l = 1:
    −θ1'θ2' sin(θ1−θ2) − 2g sin θ1 = d/dt(θ1' + 2θ2' cos(θ1−θ2)),
     θ1'θ2' sin(θ1−θ2) −  g sin θ2 = d/dt(θ2' + 2θ1' cos(θ1−θ2))."""

    def rhs(_, y):
        a, b, wa, wb = y
        c, s = np.cos(a - b), np.sin(a - b)
        r1 = -wa * wb * s - 2 * G * np.sin(a) + 2 * wb * (wa - wb) * s
        r2 = wa * wb * s - G * np.sin(b) + 2 * wa * (wa - wb) * s
        acc = np.linalg.solve([[1.0, 2 * c], [2 * c, 1.0]], [r1, r2])
        return [wa, wb, acc[0], acc[1]]

    sol = solve_ivp(rhs, (t[0], t[-1]), [th1, th2, 0.0, 0.0], method="DOP853", rtol=1e-12,
                    atol=1e-12, dense_output=True)
    assert sol.status == 0
    a, b, wa, wb = sol.sol(t)
    z = 0 * t
    x = np.stack([np.stack([np.sin(a), -np.cos(a), z], 1),
                  np.stack([np.sin(a) + np.sin(b), -np.cos(a) - np.cos(b), z], 1)], 1)
    v = np.stack([np.stack([wa * np.cos(a), wa * np.sin(a), z], 1),
                  np.stack([wa * np.cos(a) + wb * np.cos(b), wa * np.sin(a) + wb * np.sin(b), z], 1)], 1)
    return C.Trajectory(t=t, x=x, v=v)


def test_stationarity_true_motion_versus_misprinted_equations():
    system = double_pendulum(0.5, 0.8)
    model = assemble(system)
    t = np.linspace(0.0, 0.6, 1001)  # the printed equations' motion is regular this long
    eps = (1e-3, 5e-4, 2.5e-4, 1.25e-4)
    true = C.simulate(system, 0.6, rtol=1e-11, atol=1e-12, t_eval=t, model=model)
    good = stationarity(model, true, eps_list=eps)
    wrong = stationarity(model, misprinted_double_pendulum(0.5, 0.8, t), eps_list=eps)
    # δS/ε → 0 (second order) for the true motion ...
    assert good.order == pytest.approx(2.0, abs=0.05) and good.ratio < 0.15
    assert good.is_stationary and abs(good.first_variation) < 1e-6
    # ... and stays finite (first order) for the printed equations' motion
    assert wrong.order == pytest.approx(1.0, abs=0.15) and wrong.ratio > 0.7
    assert not wrong.is_stationary and abs(wrong.first_variation) > 0.1
    assert np.all(np.abs(wrong.delta_S_over_eps) > 0.5)
    # the varied paths leave the constraints at second order only
    assert np.all(np.diff(np.log(good.constraint_violation)) < -1.2)


def test_stationarity_of_the_scene_double_pendulum():
    scene = C.load_scene(Path(__file__).resolve().parents[1] / "scenarios" / "double_pendulum.toml")
    traj = C.simulate(scene.system, 2.0, rtol=1e-10, atol=1e-10, t_eval=np.linspace(0, 2, 2001))
    res = stationarity(scene.system, traj)  # default ε from 1e-2 down
    assert res.order == pytest.approx(2.0, abs=0.05) and res.ratio == pytest.approx(0.125, rel=0.1)
    S = action(scene.system, traj)
    assert S.quadrature == "simpson" and S.cumulative[0] == 0 and S.total == pytest.approx(S.cumulative[-1])


# --- bad input -----------------------------------------------------------------------------


def test_bad_input_messages():
    s = planar_pendulum(0.3)
    with pytest.raises(C.InputError, match=r"end configuration violates constraint 'distance.*by 0\.5"):
        stationary_path(s, bob(0.3), [0.0, -1.5, 0.0], 1.0)
    with pytest.raises(C.InputError, match="must be > 0"):
        stationary_path(s, bob(0.3), bob(0.1), 0.0)
    with pytest.raises(C.InputError, match="must be > 0"):
        stationary_path(s, bob(0.3), bob(0.1), -1.0)
    with pytest.raises(C.InputError, match="nodes"):
        stationary_path(s, bob(0.3), bob(0.1), 1.0, nodes=1)
    with pytest.raises(C.InputError, match="quadrature"):
        stationary_path(s, bob(0.3), bob(0.1), 1.0, quadrature="simpson")
    s.add(C.Damping(0.1))
    with pytest.raises(C.InputError, match="not in L = T − V − U"):
        stationary_path(s, bob(0.3), bob(0.1), 1.0)


def test_not_converging_raises_with_the_last_iterate():
    s = planar_pendulum(0.3)
    with pytest.raises(C.SimulationError, match="did not find a stationary path") as info:
        stationary_path(s, bob(0.3), bob(-1.2), 1.0, nodes=50, max_iter=1)
    assert info.value.trajectory is not None and info.value.trajectory.x.shape == (51, 1, 3)
    assert info.value.path.converged is False


def test_end_configuration_parsing(tmp_path):
    s = double_pendulum()
    x = end_configuration("p1=[0,-1,0]; p2=[0, -2, 0]", s)
    assert np.allclose(x, [[0, -1, 0], [0, -2, 0]])
    with pytest.raises(C.InputError, match="no end position for p2"):
        end_configuration("p1=[0,-1,0]", s)
    with pytest.raises(C.InputError, match="unknown particle 'p3'"):
        end_configuration("p3=[0,-1,0]", s)
    with pytest.raises(C.InputError, match="3 numbers"):
        end_configuration("p1=[0,-1]; p2=[0,-2,0]", s)


# --- command line --------------------------------------------------------------------------

PENDULUM = """\
[scene]
name = "pendulum"

[[particles]]
name = "bob"
mass = 1.0
position = [0.29552020666133955, -0.955336489125606, 0.0]

[[constraints]]
type = "distance"
a = "bob"
point = [0.0, 0.0, 0.0]
length = 1.0

[[constraints]]
type = "plane"
particles = ["bob"]
normal = [0.0, 0.0, 1.0]

[[effects]]
type = "gravity"
g = [0.0, -9.81, 0.0]
"""


def test_cli_path(tmp_path, capsys):
    scene = tmp_path / "pendulum.toml"
    scene.write_text(PENDULUM)
    out = tmp_path / "out"
    to = f"bob=[{float(np.sin(-0.2))!r}, {-float(np.cos(-0.2))!r}, 0]"
    assert main(["path", str(scene), "--to", to, "--time", "0.8", "--nodes", "60", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "converged" in text and "minimum" in text and "action S =" in text
    assert (out / "path.npz").is_file() and (out / "path.png").is_file()
    tr = C.Trajectory.load(out / "path.npz")
    assert tr.x.shape == (61, 1, 3) and np.allclose(tr.x[-1, 0], [np.sin(-0.2), -np.cos(-0.2), 0])
    # --to a trajectory file: its last positions
    assert main(["path", str(scene), "--to", str(out / "path.npz"), "--time", "1.5", "--nodes", "60",
                 "--out", str(tmp_path / "o2"), "--quiet"]) == 0


@pytest.mark.parametrize("args, fragment", [
    (["--to", "bob=[0, -1.5, 0]", "--time", "1"], "violates constraint 'distance"),
    (["--to", "bob=[0, -1, 0]", "--time", "0"], "--time must be a positive number"),
    (["--to", "nobody=[0, -1, 0]", "--time", "1"], "unknown particle 'nobody'"),
    (["--to", str(Path("missing.npz")), "--time", "1"], "no such file"),
])
def test_cli_path_bad_input_exits_2(tmp_path, capsys, args, fragment):
    scene = tmp_path / "pendulum.toml"
    scene.write_text(PENDULUM)
    out = tmp_path / "out"
    assert main(["path", str(scene), *args, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("constrained: error: ") and fragment in err and "Traceback" not in err
    assert not out.exists()


def test_cli_path_not_converged_exits_1_with_last_iterate(tmp_path, capsys):
    scene = tmp_path / "pendulum.toml"
    scene.write_text(PENDULUM)
    out = tmp_path / "out"
    to = f"bob=[{float(np.sin(-1.2))!r}, {-float(np.cos(-1.2))!r}, 0]"
    assert main(["path", str(scene), "--to", to, "--time", "1", "--nodes", "50", "--max-iter", "1",
                 "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "did not find a stationary path" in err and "last iterate is saved" in err
    assert (out / "path.npz").is_file()
