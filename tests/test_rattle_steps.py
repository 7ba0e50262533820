"""RATTLE at any step (issue 26, item 5): a smaller step never breaks the symplectic method,
and the step size is an input of its compiled loop (a new dt compiles nothing)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

import constrained as C
from constrained.codegen import compiled as compiled_evaluation

FOURBAR = Path(__file__).resolve().parents[1] / "scenarios" / "four_bar_linkage.toml"
STEPS = (1e-3, 7e-4, 2e-4, 1e-4, 5e-5)
COMPILED = [False] + ([True] if shutil.which("cc") else [])


@pytest.mark.parametrize("compiled", COMPILED, ids=lambda c: "compiled" if c else "virtual machine")
def test_rattle_on_the_four_bar_at_every_step_keeps_its_constraints_and_energy(compiled):
    """The bundled four-bar (two particles, three rods, a plane) for 2 s: the constraints to
    round-off at every step size, and the energy error of a second-order symplectic method,
    bounded and falling as dt² (halving dt quarters it)."""
    system = C.load_scene(FOURBAR).system
    spread = {}
    for dt in STEPS:
        tr = C.simulate(system, 2.0, method="rattle", dt=dt, compiled=compiled,
                        outputs={"constraint_residual", "energy"})
        assert np.all(np.isfinite(tr.x)) and tr.t[-1] == 2.0
        assert np.max(tr.constraint_residual) < 1e-12
        spread[dt] = np.ptp(tr.energy)
    for big, small in ((2e-4, 1e-4), (1e-4, 5e-5)):
        assert spread[big] / spread[small] == pytest.approx((big / small) ** 2, rel=0.05)
    assert spread[1e-3] < 1e-3 * abs(np.mean(tr.energy))


def test_a_new_step_size_or_parameter_value_compiles_nothing(monkeypatch):
    """dt, the row scales and the parameters are inputs of the chained steps: runs at three
    step sizes and two masses share one set of Functions (one compile at most, none if an
    earlier test of this process built them)."""
    calls = []
    original = compiled_evaluation.compile_functions

    def counted(functions):
        calls.append(len(functions))
        return original(functions)

    monkeypatch.setattr(compiled_evaluation, "compile_functions", counted)
    for dt, mass in ((1e-3, 1.0), (2.5e-4, 1.0), (3e-4, 2.0)):
        scene = C.load_scene(FOURBAR, [f"particles.B.mass={mass}"])
        tr = C.simulate(scene.system, 0.2, method="rattle", dt=dt, compiled=True,
                        outputs={"constraint_residual"})
        assert np.max(tr.constraint_residual) < 1e-12
    assert len(calls) <= 1


def test_a_step_off_the_scenes_output_grid_says_which_key_to_change(tmp_path, capsys):
    """The bundled four-bar writes every 0.01 s: --set simulate.dt=6.1e-4 does not divide it.
    The refusal named t_eval, a Python argument the scene's user never wrote; it names the
    scene key now, and a dt that divides output_dt runs."""
    from constrained.cli.main import main

    args = ["run", str(FOURBAR), "--out", str(tmp_path / "out"), "--quiet",
            "--set", 'simulate.method="rattle"', "--set", "simulate.t_end=0.2"]
    assert main([*args, "--set", "simulate.dt=6.1e-4"]) == 2
    err = capsys.readouterr().err
    assert "simulate.output_dt" in err and "multiple of dt" in err and "Traceback" not in err, err
    assert main([*args, "--set", "simulate.dt=5e-4"]) == 0
