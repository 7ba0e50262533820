"""The Jacobi integral h = Σ q̇ ∂L/∂q̇ − L of driven (rheonomic) scenes (issue 19)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import constrained as C

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"


@pytest.fixture(scope="module")
def hoop():
    scene = C.load_scene(SCENARIOS / "bead_on_rotating_hoop.toml")
    rm = C.ReducedModel.from_scene(scene)
    return scene, rm, rm.solve(4.0, rtol=1e-11, atol=1e-12, t_eval=np.linspace(0, 4, 401))


def test_hoop_jacobi_integral_is_conserved_while_energy_is_not(hoop):
    _, rm, traj = hoop
    assert rm.rheonomic and rm.jacobi_integral_conserved()
    cons = C.conservation(rm, traj)
    assert cons.jacobi_integral_conserved and not cons.hamiltonian_is_energy
    assert cons.jacobi_integral_drift < 1e-9
    assert cons.energy_drift > 0.1  # T + V changes by order one: the motor does work
    # h in closed form for R = m = 1: ½ th'² − ½ w² sin² th − g cos th
    w, g = 4.0, 9.81
    th, thd = traj.info["q"][:, 0], traj.info["q_dot"][:, 0]
    h = 0.5 * thd**2 - 0.5 * w**2 * np.sin(th) ** 2 - g * np.cos(th)
    assert np.allclose(cons.jacobi_integral, h, atol=1e-9)
    assert traj.info["jacobi_integral_conserved"] is True


def test_summary_says_conserved_only_with_a_reason_and_never_with_a_missing_value(hoop):
    _, rm, traj = hoop
    text = C.conservation(rm).summary()  # no trajectory: no value
    assert "Jacobi integral" in text and "not measured" in text and "drift" in text
    assert "None" not in text
    measured = C.conservation(rm, traj).summary()
    assert "measured drift" in measured and "None" not in measured and "h ≠ T + V" in measured


def test_crosscheck_reports_the_jacobi_integral_of_a_driven_scene(hoop):
    scene, _, _ = hoop
    cc = C.cross_check(scene, t_end=2.0)
    line = cc.jacobi_integral_line()
    assert line.startswith("Jacobi integral") and "conserved" in line and "not a constant" not in line
    assert line in cc.table()
    h = cc.jacobi_integral
    assert np.max(np.abs(h - h[0])) < 1e-7 * abs(h[0])
    e = cc.reduced.energy
    assert np.max(np.abs(e - e[0])) > 1.0


def test_explicitly_time_dependent_lagrangian_has_no_jacobi_integral():
    kapitza = C.ReducedModel.from_scene(C.load_scene(SCENARIOS / "kapitza_pendulum.toml"))
    assert not kapitza.jacobi_integral_conserved()  # the pivot's motion enters L through t
    cons = C.conservation(kapitza)
    assert not cons.jacobi_integral_conserved and "not conserved" in cons.summary()
    damped = C.ReducedModel.from_scene(C.load_scene(SCENARIOS / "damped_hanging_spring.toml"))
    assert not damped.jacobi_integral_conserved()  # damping: a non-conservative force


def test_free_scene_jacobi_integral_is_the_energy():
    rm = C.ReducedModel.from_scene(C.load_scene(SCENARIOS / "double_pendulum.toml"))
    cons = C.conservation(rm)
    assert rm.jacobi_integral_conserved() and cons.hamiltonian_is_energy and "h = T + V" in cons.summary()
