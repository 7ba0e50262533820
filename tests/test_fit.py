"""Exact sensitivities of a run, and least-squares fits of [parameters] to measurements.

The sensitivities are checked against a high-order (5-point) central finite difference of
whole runs at tight tolerances — in the tests only: the library differentiates with CasADi.
The fits recover known parameters from synthetic noisy data to within the standard errors
they state, and the spread of many fits (run through Dask) is the standard error.
"""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import constrained as C
from constrained.cli.main import main

ROOT = Path(__file__).resolve().parents[1]
SCENE = str(ROOT / "scenarios" / "pendulum_fit.toml")
CAMERA = str(ROOT / "scenarios" / "data" / "pendulum_camera.csv")
TRUE = {"l": 0.75, "b": 0.03, "th0": 0.35}


def five_point(f, h):
    """(−f(2h) + 8 f(h) − 8 f(−h) + f(−2h)) / 12h: error O(h⁴)."""
    return (-f(2 * h) + 8 * f(h) - 8 * f(-h) + f(-2 * h)) / (12 * h)


def run_values(system, t, outputs_of, **kw):
    run = C.simulate(system, float(t[-1]), t_eval=t, method="dopri", rtol=1e-12, atol=1e-14, **kw)
    return outputs_of(run)


def test_sensitivities_to_parameters_equal_a_high_order_finite_difference():
    scene = C.load_scene(ROOT / "scenarios" / "double_pendulum_parametric.toml")
    system = scene.system
    t = np.array([0.0, 0.4, 1.3])
    sens = C.sensitivities(system, t, outputs=["x_p2", "y_p1", "Fx_p1", "vy_p2"],
                           parameters=["l1", "m2", "g", "th2"])
    assert sens.values.shape == (3, 4) and sens.d_parameters.shape == (3, 4, 4)

    def outputs_of(run):  # the same observables from a run: forces from the run's KKT solve
        return np.column_stack([run.x[:, 1, 0], run.x[:, 0, 1], run.constraint_forces[:, 0, 0],
                                run.v[:, 1, 1]])

    np.testing.assert_allclose(sens.values, run_values(system, t, outputs_of), atol=1e-9)
    for j, name in enumerate(sens.parameters):
        base = system.parameters[name]
        fd = five_point(lambda h, name=name, base=base: run_values(system, t, outputs_of,
                                                                    parameters={name: base + h}), 1e-3)
        np.testing.assert_allclose(sens.d_parameters[:, :, j], fd, atol=1e-6 * max(1.0, np.abs(fd).max()))


def test_forward_and_adjoint_agree_and_the_initial_state_derivative_is_tangent():
    s = C.System(name="3D chain, uneven grams")
    masses, lengths = [0.004, 0.011, 0.002], [0.03, 0.017, 0.025]
    directions = np.array([[0.3, -1.0, 0.1], [-0.2, -1.0, 0.4], [0.5, -0.7, -0.2]])
    lengths = np.array(lengths)
    x = np.cumsum(lengths[:, None] * directions / np.linalg.norm(directions, axis=1)[:, None], axis=0)
    for i, m in enumerate(masses):
        s.add_particle(f"p{i}", m, x[i])
    s.add(C.Distance("p0", point=[0, 0, 0], length=lengths[0]))
    for i in (1, 2):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=lengths[i]))
    s.add(C.Gravity([0, "-g", 0]), C.Damping("c", particles=["p2"]))
    s.set_parameter("g", 9.81)
    s.set_parameter("c", 0.002)
    t = np.linspace(0.0, 0.3, 4)
    fwd = C.sensitivities(s, t, outputs=["x_p2", "z_p1"], initial_state=True, mode="forward")
    adj = C.sensitivities(s, t, outputs=["x_p2", "z_p1"], initial_state=True, mode="adjoint")
    np.testing.assert_allclose(fwd.jacobian(), adj.jacobian(), rtol=1e-10, atol=1e-12)

    def x_p2(run):
        return np.column_stack([run.x[:, 2, 0], run.x[:, 1, 2]])

    x0 = s.positions
    for particle, axis in ((2, 0), (1, 2)):
        def moved(h, particle=particle, axis=axis):
            x = x0.copy()
            x[particle, axis] += h
            return run_values(s.with_state(x), t, x_p2)

        fd = five_point(moved, 1e-5)
        np.testing.assert_allclose(fwd.d_x0[:, :, particle, axis], fd, atol=1e-6)
    # moving the start along a rod (normal to the manifold) is undone by the projection
    radial = x0[0] / np.linalg.norm(x0[0])
    assert np.abs(np.einsum("tkc,c->tk", fwd.d_x0[:, :, 0], radial)).max() < 1e-8


def test_the_shipped_camera_data_gives_back_the_true_length_and_damping():
    data = C.read_measurements(CAMERA)
    assert data.names == ("x_bob", "y_bob") and len(data.t) == 151
    result = C.fit(C.load_scene(SCENE).system, data, ["l", "b"])
    assert result.success
    for name in ("l", "b"):
        k = result.names.index(name)
        assert abs(result.estimates[k] - TRUE[name]) < 3 * result.standard_errors[k], result.table()
    assert result.standard_errors[0] < 1e-3 and result.standard_errors[1] < 1e-3
    np.testing.assert_allclose(result.rms, 1e-3, rtol=0.15)  # the noise the script added
    assert abs(result.correlation[0, 1]) < 0.5


def test_the_data_script_writes_the_shipped_file(tmp_path):
    out = tmp_path / "camera.csv"
    script = ROOT / "scenarios" / "data" / "make_pendulum_camera.py"
    done = subprocess.run([sys.executable, str(script), str(out)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    shipped = np.loadtxt(CAMERA, delimiter=",", skiprows=1)
    np.testing.assert_allclose(np.loadtxt(out, delimiter=",", skiprows=1), shipped, atol=2e-6)


def synthetic(seed: int, noise=0.002, sigma_column=False) -> C.Measurements:
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 4.0, 81)
    run = C.simulate(C.load_scene(SCENE).system, 4.0, t_eval=t, rtol=1e-11, atol=1e-13, parameters=TRUE)
    theta = np.arctan2(run.x[:, 0, 0], -run.x[:, 0, 1]) + noise * rng.standard_normal(len(t))
    sigma = np.full((len(t), 1), noise) if sigma_column else None
    return C.Measurements(t, ("theta",), theta[:, None], sigma)


def test_an_angle_with_its_sigma_fits_three_parameters_with_chi2_per_dof_near_one():
    data = synthetic(3, sigma_column=True)
    result = C.fit(C.load_scene(SCENE).system, data, ["l", "b", "th0"],
                   observables={"theta": "atan2(x_bob, -y_bob)"}, bounds={"l": (0.1, 5.0), "b": (0.0, 1.0)})
    assert result.success and result.sigma_given
    assert 0.6 < result.reduced_chi2 < 1.5
    for k, name in enumerate(result.names):
        assert abs(result.estimates[k] - TRUE[name]) < 3.5 * result.standard_errors[k], result.table()


@pytest.mark.skipif(importlib.util.find_spec("distributed") is None, reason="Dask is not installed")
def test_a_sweep_of_fits_on_dask_scatters_as_its_standard_errors_say(tmp_path):
    import distributed

    draws = [synthetic(seed) for seed in range(8)]
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        sweep = C.fit_sweep(SCENE, draws, ["l", "b"], scheduler=client,
                            observables={"theta": "atan2(x_bob, -y_bob)"})
    assert sweep.where.startswith("Dask") and sweep.failed == 0
    est, se = sweep.estimates(), sweep.standard_errors()
    truth = np.array([TRUE["l"], TRUE["b"]])
    # each draw's error, in its own standard errors: unit variance (chi-square, 16 values)
    z = (est - truth) / se
    assert 0.3 < np.mean(z**2) < 2.2, z
    # the scatter of the estimates is the stated standard error
    np.testing.assert_allclose(est.std(axis=0, ddof=1), se.mean(axis=0), rtol=0.6)


def test_a_parameter_the_data_cannot_see_is_reported_not_inverted():
    scene = C.load_scene(SCENE)
    system = scene.system.with_parameters({"b": 0.0}).copy()  # no damping: the mass is invisible
    system.set_parameter("m", 0.2)
    system.particles[0].formulas["mass"] = "m"
    data = synthetic(1)
    result = C.fit(system, data, ["l", "m"], observables={"theta": "atan2(x_bob, -y_bob)"},
                   start={"l": 0.7}, sigma=0.002, bounds={"m": (0.01, 10.0)})
    assert not np.isfinite(result.standard_errors[1]) and result.unidentified
    assert "NOT determined" in result.table()


def test_measurement_files_are_checked_line_by_line(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("t,x_bob\n0,0.1\n0.1,abc\n")
    with pytest.raises(C.InputError, match="line 3, column 'x_bob'"):
        C.read_measurements(bad)
    bad.write_text("time,x_bob\n0,0.1\n")
    with pytest.raises(C.InputError, match="no column 't'"):
        C.read_measurements(bad)
    bad.write_text("t,x_bob\n0.2,0.1\n0.1,0.2\n")
    with pytest.raises(C.InputError, match="strictly increasing"):
        C.read_measurements(bad)
    bad.write_text("t,x_bob,sigma_y_bob\n0,0.1,0.01\n")
    with pytest.raises(C.InputError, match="sigma_y_bob"):
        C.read_measurements(bad)
    ok = tmp_path / "gaps.csv"
    ok.write_text("t,x_bob,y_bob\n0,0.1,\n0.1,NA,-0.7\n")
    data = C.read_measurements(ok)
    assert data.count == 2
    system = C.load_scene(SCENE).system
    with pytest.raises(C.InputError, match="not among the scene's"):
        C.fit(system, data, ["length"])
    with pytest.raises(C.InputError, match="cannot determine"):
        C.fit(system, data, ["l", "b", "th0"])
    with pytest.raises(C.InputError, match="observables.x_bob.*y_ball"):
        C.fit(system, data, ["l"], observables={"x_bob": "x_bob + y_ball"})
    with pytest.raises(C.InputError, match="scene.system"):
        C.fit(C.load_scene(SCENE), data, ["l"])


def test_cli_fit_writes_estimates_figures_and_the_fitted_run(tmp_path, capsys):
    out = tmp_path / "fit"
    code = main(["fit", SCENE, CAMERA, "--params", "l,b", "--out", str(out), "--bounds", "l=0.1:3"])
    text = capsys.readouterr().out
    assert code == 0, text
    assert "std. error" in text and "converged" in text
    report = json.loads((out / "fit.json").read_text())
    est = {p["name"]: p for p in report["parameters"]}
    assert abs(est["l"]["estimate"] - TRUE["l"]) < 3 * est["l"]["standard_error"]
    run = C.Trajectory.load(out / "trajectory.npz")
    assert run.t[-1] == pytest.approx(5.0)
    for name in ("fit.png", "residuals.png", "fit.csv"):
        assert (out / name).stat().st_size > 1000
    assert main(["fit", SCENE, CAMERA, "--params", "nope", "--out", str(out)]) == 2
    assert "nope" in capsys.readouterr().err
    assert main(["fit", SCENE, str(tmp_path / "missing.csv"), "--params", "l", "--out", str(out)]) == 2
    assert "no such file" in capsys.readouterr().err


@pytest.mark.slow
def test_ctrl_c_stops_a_fit_promptly_with_status_130(tmp_path):
    import time

    from interrupting import interrupt_when

    t = np.linspace(0.0, 60.0, 3001)
    rows = "\n".join(f"{ti:.6f},{0.3 * np.cos(3.6 * ti):.6f}" for ti in t)  # far from the model
    (tmp_path / "long.csv").write_text("t,x_bob\n" + rows + "\n")
    began = time.monotonic()
    args = ["fit", SCENE,
            str(tmp_path / "long.csv"), "--params", "l,b,th0", "--out", str(tmp_path / "out"), "--quiet"]
    code, seconds, err = interrupt_when(args, lambda: time.monotonic() - began > 3.0, cwd=tmp_path.parent,
                                        settle=0.0)
    assert code == 130, err
    assert seconds < 5.0 and "Traceback" not in err
    assert not (tmp_path / "out" / "fit.json").exists()


def test_a_load_cell_on_the_rod_is_an_observable_too():
    """The rod's tension, sqrt(Fx² + Fy²) of the constraint force on the bob, measured alone,
    gives back the length and the damping."""
    system = C.load_scene(SCENE).system
    t = np.linspace(0.0, 3.0, 61)
    run = C.simulate(system, 3.0, t_eval=t, rtol=1e-11, atol=1e-13, parameters=TRUE)
    tension = np.linalg.norm(run.constraint_forces[:, 0, :2], axis=1)
    noise = 1e-4  # newtons
    measured = tension[:, None] + noise * np.random.default_rng(4).standard_normal((61, 1))
    data = C.Measurements(t, ("tension",), measured)
    result = C.fit(system, data, ["l", "b"], observables={"tension": "sqrt(Fx_bob**2 + Fy_bob**2)"},
                   sigma=noise)
    assert result.success
    for k, name in enumerate(result.names):
        assert abs(result.estimates[k] - TRUE[name]) < 3.5 * result.standard_errors[k], result.table()


def test_systems_of_one_structure_with_other_plain_starts_get_their_own_start():
    """The replay graph is shared by every system of a structure: a start written as numbers
    enters as numbers, not as the first system's."""
    a = C.load_scene(SCENE).system  # start given by formulas of l and th0
    b = a.copy()
    b.particles[0].formulas.pop("position")
    b = b.with_state([[0.7 * np.sin(0.5), -0.7 * np.cos(0.5), 0.0]])  # the same structure, a number start
    t = [0.5, 1.0]
    for system in (a, b, a):
        sens = C.sensitivities(system, t, parameters=["l"])
        run = C.simulate(system, 1.0, t_eval=t, method="dopri", rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(sens.values, run.x.reshape(2, -1), atol=1e-12)
