"""Scene.run(): the Python API runs a scene with its own settings and [expect] (issue 19)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import constrained as C

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"


def test_run_uses_the_scene_settings_and_checks_expect():
    scene = C.load_scene(SCENARIOS / "simple_spring.toml")
    result = scene.run()
    traj = result.trajectory
    s = scene.settings
    assert traj.t[0] == pytest.approx(s["t_start"]) and traj.t[-1] == pytest.approx(s["t_end"])
    assert s["output_dt"] == 0.01  # the scene's own output grid
    assert len(traj.t) == round((s["t_end"] - s["t_start"]) / s["output_dt"]) + 1
    assert np.allclose(np.diff(traj.t), s["output_dt"])
    keys = [r.key for r in result.expectations]
    assert len(keys) == len(scene.expectations) and keys
    assert result.ok and result.failed == []
    assert "checks pass" in result.report()
    again, checks = scene.run()  # unpacks like (trajectory, checks)
    assert np.allclose(again.x, traj.x) and len(checks) == len(keys)


def test_run_with_overrides_is_the_cli_set_and_leaves_the_scene_alone():
    scene = C.load_scene(SCENARIOS / "simple_spring.toml")
    t_end = scene.settings["t_end"]
    short = scene.run(["simulate.t_end=1.5"])
    assert short.trajectory.t[-1] == pytest.approx(1.5)
    assert scene.settings["t_end"] == t_end  # the Scene itself is not changed
    wrong = scene.run(["simulate.t_end=1.5", "parameters.k=9"])  # the closed form no longer holds
    assert not wrong.ok and any("closed_form" in r.key for r in wrong.failed)
    with pytest.raises(C.InputError, match="no_such_key"):
        scene.run(["simulate.no_such_key=1"])


def test_run_matches_simulate_with_the_same_settings_by_hand():
    scene = C.load_scene(SCENARIOS / "double_pendulum.toml")
    result = scene.run(["simulate.t_end=0.5", "simulate.samples=11"])
    s = result.scene.settings
    by_hand = C.simulate(scene.system, 0.5, method=s["method"], rtol=s["rtol"], atol=s["atol"],
                         t_eval=np.linspace(0, 0.5, 11))
    assert np.allclose(result.trajectory.x, by_hand.x, atol=1e-12)
    assert result.trajectory.constraint_forces is not None  # [outputs] quantities


def test_run_method_reduced_and_quantities():
    scene = C.load_scene(SCENARIOS / "simple_pendulum.toml")
    result = scene.run(["simulate.t_end=0.5", "simulate.method=reduced", "expect={}"],
                       quantities=["energy"])
    assert result.trajectory.energy is not None and result.expectations == [] and result.ok
    assert result.trajectory.multipliers is None


def test_run_without_end_time_is_refused(tmp_path):
    text = (SCENARIOS / "free_particle.toml").read_text()
    lines = [ln for ln in text.splitlines() if not ln.strip().startswith("t_end")]
    path = tmp_path / "no_end.toml"
    path.write_text("\n".join(lines) + "\n")
    scene = C.load_scene(path)
    with pytest.raises(C.InputError, match="t_end"):
        scene.run()
