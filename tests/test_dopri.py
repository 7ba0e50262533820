"""dopri: the Dormand–Prince step loop run by CasADi — accuracy, drift, outputs, bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import DP_REF_T2, double_pendulum
from test_solvers import driven_pendulum

import constrained as C
from constrained.codegen import compiled
from constrained.model.cache import structure_cache
from constrained.model.structure import Structure


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("CONSTRAINED_CACHE", str(tmp_path / "cache"))


@pytest.mark.parametrize("base, rtol, max_error", [("DOP853", 1e-10, 1e-9), ("DOPRI5", 1e-11, 1e-9),
                                                  ("Tsit5", 1e-11, 1e-9)])
def test_dopri_reaches_the_double_pendulum_reference(base, rtol, max_error):
    tr = C.simulate(double_pendulum(), 2.0, method="dopri", base=base, rtol=rtol, atol=rtol * 1e-2,
                    t_eval=np.linspace(0, 2, 11), compiled=False)
    assert np.allclose(tr.t, np.linspace(0, 2, 11), rtol=0, atol=1e-15)  # lands on every output
    assert np.max(np.abs(tr.x[-1, :, :2] - DP_REF_T2)) <= max_error
    assert np.max(tr.constraint_residual) <= 1e-12  # projected after every step
    assert tr.stats["steps"] > 0 and tr.stats["nfev"] >= 6 * tr.stats["steps"]


def test_dopri_error_falls_with_the_tolerance_at_its_order():
    errors = []
    for rtol in (1e-7, 1e-9):
        tr = C.simulate(double_pendulum(), 2.0, method="dopri", rtol=rtol, atol=rtol * 1e-2,
                        t_eval=[0.0, 2.0], outputs=set(), compiled=False)
        errors.append(np.max(np.abs(tr.x[-1, :, :2] - DP_REF_T2)))
    assert errors[1] < errors[0] / 20  # tolerance proportionality: roughly 100x per 100x in rtol


def test_dopri_without_outputs_returns_every_accepted_step_and_conserves_energy():
    tr = C.simulate(double_pendulum(), 5.0, method="dopri", rtol=1e-10, atol=1e-12, compiled=False)
    assert len(tr.t) == tr.stats["steps"] + 1 and tr.t[-1] == 5.0
    assert np.all(np.diff(tr.t) > 0)
    assert np.ptp(tr.energy) <= 1e-7 * np.max(np.abs(tr.energy))


def test_dopri_follows_a_rheonomic_constraint_like_projection():
    t = np.linspace(0, 2, 11)
    ref = C.simulate(driven_pendulum(), 2.0, rtol=1e-12, atol=1e-12, t_eval=t)
    tr = C.simulate(driven_pendulum(), 2.0, method="dopri", rtol=1e-11, atol=1e-12, t_eval=t, compiled=False)
    assert np.max(np.abs(tr.x - ref.x)) <= 1e-9
    assert np.max(tr.constraint_residual) <= 1e-12


def test_dopri_is_exact_for_free_fall():
    s = C.System(name="throw")
    s.add_particle("ball", 0.5, [0.0, 1.0, 0.0], [2.0, 3.0, -1.0])
    s.add(C.Gravity([0, -9.81, 0]))
    tr = C.simulate(s, 1.5, method="dopri", base="DOPRI5", rtol=1e-6, atol=1e-8, t_eval=[0.0, 1.5],
                    compiled=False)
    t = 1.5
    expected = np.array([2.0 * t, 1.0 + 3.0 * t - 0.5 * 9.81 * t * t, -t])
    assert np.allclose(tr.x[-1, 0], expected, rtol=0, atol=1e-12)


@pytest.mark.skipif(compiled.compiler() is None, reason="no C compiler on this machine")
def test_compiled_dopri_matches_the_virtual_machine():
    model = C.assemble(double_pendulum())
    t = np.linspace(0, 2, 5)
    vm = C.simulate(double_pendulum(), 2.0, method="dopri", base="DOPRI5", rtol=1e-9, atol=1e-11,
                    t_eval=t, compiled=False, model=model)
    mc = C.simulate(double_pendulum(), 2.0, method="dopri", base="DOPRI5", rtol=1e-9, atol=1e-11,
                    t_eval=t, compiled=True, model=model)
    assert vm.stats["evaluation"] == "virtual machine" and mc.stats["evaluation"] == "compiled"
    assert mc.stats["steps"] == vm.stats["steps"]
    assert np.max(np.abs(mc.x - vm.x)) <= 1e-12 and np.max(np.abs(mc.v - vm.v)) <= 1e-12
    again = C.simulate(double_pendulum(), 2.0, method="dopri", base="DOPRI5", rtol=1e-7, atol=1e-9,
                       t_eval=t, compiled=True, model=model)
    # built once per structure and setting: the tolerances are inputs of the compiled loop
    cache, prefix = structure_cache(model)
    loops = sorted(key for key in cache if key[len(prefix):len(prefix) + 2] == ("dopri", "DOPRI5"))
    assert loops == [(*prefix, "dopri", "DOPRI5", False, None), (*prefix, "dopri", "DOPRI5", True, None)]
    assert again.stats["steps"] < mc.stats["steps"]


PARAMETRIC = Path(__file__).resolve().parent.parent / "scenarios" / "double_pendulum_parametric.toml"


@pytest.mark.parametrize("compiled_loop", [False, pytest.param(True, marks=pytest.mark.skipif(
    compiled.compiler() is None, reason="no C compiler on this machine"))])
def test_new_parameter_values_reuse_the_step_loop_and_match_a_rebuild(compiled_loop):
    """Masses, lengths, g and the start angles are parameters: new values run the same
    (compiled) step loop — nothing is built again — and end where a model assembled anew
    for those values ends."""
    scene = C.load_scene(PARAMETRIC)
    model = C.assemble(scene.system)
    kw = dict(method="dopri", rtol=1e-10, atol=1e-10, outputs=[], compiled=compiled_loop)
    C.simulate(scene.system, 1.0, model=model, **kw)
    cache, _ = structure_cache(model)
    built = set(cache)
    builds = Structure.builds
    for values in ({"m1": 1.7, "l2": 0.8}, {"g": 3.7, "th1": 1.1, "m2": 0.4}):
        tr = C.simulate(scene.system, 1.0, model=model, parameters=values, **kw)
        fresh = C.assemble(scene.system.with_parameters(values), reuse=False)
        ref = C.simulate(scene.system.with_parameters(values), 1.0, model=fresh,
                         **{**kw, "compiled": False})
        np.testing.assert_allclose(tr.x[-1], ref.x[-1], rtol=0, atol=1e-12)
        assert tr.stats["evaluation"] == ("compiled" if compiled_loop else "virtual machine")
    assert set(cache) == built and Structure.builds == builds + 2  # (the two fresh references)


def test_dopri_refuses_bad_settings_and_takes_redundant_constraints():
    with pytest.raises(C.InputError, match="unknown base tableau 'RK4'"):
        C.simulate(double_pendulum(), 0.1, method="dopri", base="RK4")
    with pytest.raises(C.InputError, match="max_steps"):
        C.simulate(double_pendulum(), 0.1, method="dopri", max_steps=0)
    s = C.System(name="twice pinned")
    s.add_particle("p", 1.0, [1.0, 0.0, 0.0])
    s.add(C.Distance("p", point=[0, 0, 0], length=1.0), C.Distance("p", point=[0, 0, 0], length=1.0))
    s.add(C.Gravity([0, -9.81, 0]))
    tr = C.simulate(s, 0.5, method="dopri", compiled=False)
    # one independent row carries the pendulum; the two identical rods share its tension
    np.testing.assert_allclose(tr.multipliers[:, 0], tr.multipliers[:, 1], rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(tr.x[:, 0], axis=1), 1.0, atol=1e-12)


def test_dopri_stops_with_a_message_and_keeps_what_it_computed():
    with pytest.raises(C.SimulationError, match="max_steps = 20") as info:
        C.simulate(double_pendulum(), 2.0, method="dopri", rtol=1e-12, atol=1e-14, max_steps=20,
                   compiled=False)
    kept = info.value.trajectory
    assert len(kept.t) >= 2 and kept.t[-1] < 2.0
    assert np.max(kept.constraint_residual) <= 1e-12

    def stop(t):
        if t > 0.5:
            raise KeyboardInterrupt

    with pytest.raises(C.SimulationError, match="interrupted") as info:
        C.simulate(double_pendulum(), 2.0, method="dopri", t_eval=np.linspace(0, 2, 11), progress=stop,
                   compiled=False)  # (11 outputs: each ends a step, so the run takes several calls)
    assert 0.5 <= info.value.trajectory.t[-1] < 2.0  # the outputs reached before the interrupt


@pytest.mark.parametrize("base, rtol", [("DOP853", 1e-6), ("DOP853", 1e-10), ("DOPRI5", 1e-8)])
def test_a_fine_output_grid_comes_from_the_dense_output_within_the_tolerance(base, rtol, monkeypatch):
    """More than LANDED_OUTPUTS output times (of a model of DENSE_FROM coordinates or more:
    here every model) are interpolated (degree-6 Hermite) and projected instead of each ending
    a step: no extra steps, the constraints held to round-off, and the samples about as
    accurate as landed ones (both against a run at 1e-13)."""
    from constrained.solvers import dopri
    from constrained.solvers.dopri import LANDED_OUTPUTS

    monkeypatch.setattr(dopri, "DENSE_FROM", 0)

    grid = np.linspace(0.0, 2.0, 401)
    assert len(grid) > LANDED_OUTPUTS
    kw = dict(method="dopri", base=base, rtol=rtol, atol=rtol * 1e-2, compiled=False,
              outputs=["constraint_residual"])
    fine = C.simulate(double_pendulum(), 2.0, t_eval=grid, **kw)
    coarse = C.simulate(double_pendulum(), 2.0, **kw)  # every accepted step, no outputs to land on
    assert fine.stats["steps"] == coarse.stats["steps"]  # the grid cost no steps
    np.testing.assert_array_equal(fine.t, grid)
    np.testing.assert_allclose(fine.x[-1], coarse.x[-1], rtol=0, atol=1e-14)
    assert np.max(fine.constraint_residual) <= 1e-12
    reference = C.simulate(double_pendulum(), 2.0, method="dopri", rtol=1e-13, atol=1e-15, t_eval=grid[::50],
                           compiled=False)  # 9 outputs: landed
    interpolated = np.max(np.abs(fine.x[::50] - reference.x))
    landed = np.max(np.abs(C.simulate(double_pendulum(), 2.0, t_eval=grid[::50], **kw).x - reference.x))
    assert interpolated <= max(3 * landed, 10 * rtol)


def test_a_large_model_takes_a_fine_grid_from_the_dense_output():
    """From DENSE_FROM coordinates a fine grid costs no steps (a 100-link chain, 201 outputs)."""
    from constrained.solvers.dopri import DENSE_FROM

    n = DENSE_FROM // 3
    s = C.System()
    for i in range(n):
        s.add_particle(f"p{i}", 1.0, [(i + 1) * np.sin(0.4), -(i + 1) * np.cos(0.4), 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=1.0), C.Plane([f"p{i}" for i in range(n)], [0, 0, 1]),
          C.Gravity([0, -9.81, 0]), *[C.Distance(f"p{i - 1}", f"p{i}", length=1.0) for i in range(1, n)])
    kw = dict(method="dopri", rtol=1e-6, atol=1e-8, compiled=False, outputs=["constraint_residual"])
    fine = C.simulate(s, 0.2, t_eval=np.linspace(0, 0.2, 201), **kw)
    steps = C.simulate(s, 0.2, **kw)
    assert fine.stats["steps"] == steps.stats["steps"] < 100
    np.testing.assert_allclose(fine.x[-1], steps.x[-1], rtol=0, atol=1e-13)
    assert np.max(fine.constraint_residual) <= 1e-11
    rods = np.linalg.norm(np.diff(fine.x, axis=1), axis=2)
    np.testing.assert_allclose(rods, 1.0, rtol=0, atol=1e-11)
