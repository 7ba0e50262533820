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


def _numpy_rattle(x, v, masses, force, rods, dt, steps):
    """An independent RATTLE (velocity Verlet, SHAKE by full Newton on the multipliers, the
    velocities projected on the rods): ``rods`` (a, b, length), b = None for the origin."""
    minv = np.repeat(1.0 / masses, 3)

    def f_and_J(y):
        f, J = np.zeros(len(rods)), np.zeros((len(rods), y.size))
        for k, (a, b, length) in enumerate(rods):
            d = y[3 * a:3 * a + 3] - (0.0 if b is None else y[3 * b:3 * b + 3])
            f[k] = d @ d - length**2
            J[k, 3 * a:3 * a + 3] = 2 * d
            if b is not None:
                J[k, 3 * b:3 * b + 3] = -2 * d
        return f, J

    F = force(x, v)
    for _ in range(steps):
        _, J0 = f_and_J(x)
        base = x + dt * v + 0.5 * dt**2 * minv * F
        lam = np.zeros(len(rods))
        for _ in range(30):
            f1, J1 = f_and_J(base + 0.5 * dt**2 * minv * (J0.T @ lam))
            lam -= np.linalg.solve(J1 @ (0.5 * dt**2 * minv[:, None] * J0.T), f1)
        v_half = v + 0.5 * dt * minv * (F + J0.T @ lam)
        x = x + dt * v_half
        _, J1 = f_and_J(x)
        v = v_half
        for _ in range(60):  # v_{n+1} = v½ + h/2 M⁻¹ (F(x_{n+1}, v_{n+1}) + J1ᵀ μ), J1 v_{n+1} = 0:
            v = v_half + 0.5 * dt * minv * force(x, v)  # a fixed point (contracts by h c / 2m)
            v = v - minv * (J1.T @ np.linalg.solve(J1 @ (minv[:, None] * J1.T), J1 @ v))
        F = force(x, v)  # (at x_{n+1} and v_{n+1}: the same as the last half-kick's without damping)
    return x, v


@pytest.mark.parametrize("damping", [0.0, 0.02], ids=["conservative", "damped"])
@pytest.mark.parametrize("compiled", COMPILED, ids=lambda c: "compiled" if c else "virtual machine")
def test_rattle_agrees_with_an_independent_rattle_with_pair_forces_and_gravity(compiled, damping):
    """A double pendulum of unequal masses (grams) and a free bead, all three repelling as
    ε (σ/r)¹² (a pair kernel), under gravity (and Rayleigh damping): 200 RATTLE steps agree
    with a NumPy RATTLE to 1e-10 m. Forces that depend on x alone are carried from one step to
    the next (one force evaluation per step): a stale or misplaced force would differ at
    O(dt); velocity-dependent ones are evaluated at (x_n, v_n) and (x_{n+1}, v_{n+1}) (the
    reference iterates that second half-kick to its fixed point)."""
    eps, sig, g, dt = 1e-4, 0.02, 9.81, 2e-3
    masses = np.array([0.012, 0.005, 0.02])
    x0 = np.array([0.03, -0.04, 0.0, 0.07, -0.07, 0.01, 0.05, -0.02, 0.03])
    v0 = np.array([0.0, 0.0, 0.2, 0.1, 0.0, -0.1, -0.3, 0.1, 0.0])
    rods = [(0, None, 0.05), (1, 0, np.linalg.norm(x0[3:6] - x0[:3]))]
    s = C.System(name="pendulum and bead", parameters={"eps": eps, "sig": sig})
    for i, m in enumerate(masses):
        s.add_particle(f"p{i}", m, x0[3 * i:3 * i + 3], v0[3 * i:3 * i + 3])
    s.add(C.Distance("p0", point=[0.0, 0.0, 0.0], length=0.05))
    s.add(C.Distance("p0", "p1", length=rods[1][2]))
    s.add(C.Gravity([0.0, -g, 0.0]))
    s.add(C.Pairwise("eps*(sig/r)**12"))
    if damping:
        s.add(C.Damping(damping))
    tr = C.simulate(s, 200 * dt, method="rattle", dt=dt, compiled=compiled, outputs=set())
    x0, v0 = tr.x[0].ravel(), tr.v[0].ravel()  # (the start as projected)

    def force(y, u):
        F = np.tile([0.0, -g, 0.0], 3) * np.repeat(masses, 3) - damping * u
        for i in range(3):
            for j in range(i + 1, 3):
                d = y[3 * i:3 * i + 3] - y[3 * j:3 * j + 3]
                r = np.linalg.norm(d)
                push = 12 * eps * sig**12 / r**14 * d
                F[3 * i:3 * i + 3] += push
                F[3 * j:3 * j + 3] -= push
        return F

    x, v = _numpy_rattle(x0, v0, masses, force, rods, dt, 200)
    assert np.max(np.abs(tr.x[-1].ravel() - x)) < 1e-10
    assert np.max(np.abs(tr.v[-1].ravel() - v)) < 1e-8


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
