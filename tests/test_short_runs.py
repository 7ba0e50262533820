"""Runs far shorter than the motion's time scale (docs/hard-cases.md, section 18): over 1 ps to
1 µs the motion is its Taylor polynomial x(t) = x0 + v0 t + a0 t²/2, a0 from the KKT system at
the start. `ggl` stopped at t = 0 on a 1 ns run ("IDAS stopped after t = 0 s", IDA_CONV_FAIL):
its Newton matrix, written in seconds, mixed rows of α/h with rows of 1, and at h ~ 1e-14 s the
sparse factorization lost the constraint block. It now integrates each call in the call's own
unit of time."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

import constrained as C
from constrained.cli.main import main

G = np.array([0.0, -9.81, 0.0])
SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
L, THETA, OMEGA, MASS = 0.7, 0.6, 2.0, 1.3


def swinging_pendulum():
    """A bob on a rod of length L at angle THETA from the downward vertical, swinging at OMEGA;
    a0 = g − (g·e) e − (|v0|²/L) e (gravity's tangential part and the centripetal pull, e = x0/L)."""
    x0 = L * np.array([np.sin(THETA), -np.cos(THETA), 0.0])
    v0 = OMEGA * L * np.array([np.cos(THETA), np.sin(THETA), 0.0])
    e = x0 / L
    a0 = G - (G @ e) * e - (v0 @ v0 / L) * e
    s = C.System(name="swinging pendulum")
    s.add_particle("bob", MASS, x0, v0)
    s.add(C.Distance("bob", point=[0, 0, 0], length=L), C.Gravity(list(G)))
    return s, x0, v0, a0


@pytest.mark.parametrize("method", ["ggl", "idas"])
@pytest.mark.parametrize("t_end", [1e-12, 1e-9, 1e-6])
@pytest.mark.parametrize("one_sample", [False, True], ids=["default grid", "t_end one sample"])
def test_a_tiny_run_follows_the_taylor_polynomial(method, t_end, one_sample):
    """Every sample on x0 + v0 t + a0 t²/2 and v0 + a0 t. The velocity's change a0 t is resolved
    to 1e-3 at every span (1e-14 m/s of round-off allowed: v0 is 1.4 m/s); the position's term
    a0 t²/2 (3e-12 m at 1 µs) to a quarter; below 1 ns it is under the round-off of x (4e-15 m
    allowed: idas projects each of 200 outputs), and v0 t is what is checked."""
    s, x0, v0, a0 = swinging_pendulum()
    t_eval = [0.0, t_end] if one_sample else None
    tr = C.simulate(s, t_end, method=method, rtol=1e-12, atol=1e-14, t_eval=t_eval)
    assert tr.success and tr.t[-1] == t_end and len(tr.t) == (2 if one_sample else 201)
    t = tr.t[:, None]
    x_taylor, v_taylor = x0 + v0 * t + a0 * t**2 / 2, v0 + a0 * t
    a = np.linalg.norm(a0)
    assert np.abs(tr.x[:, 0] - x_taylor).max() < 4e-15 + 0.25 * a * t_end**2 / 2
    assert np.abs(tr.v[:, 0] - v_taylor).max() < 1e-14 + 1e-3 * a * t_end
    assert np.abs(np.linalg.norm(tr.x[:, 0], axis=1) - L).max() < 1e-14


def kkt_accelerations(masses, x, v, rods):
    """a from M a = F + Jᵀλ, J a = −(J̇ v) for rods f = ½(|x_i − x_j|² − ℓ²): row d = x_i − x_j
    on particle i and −d on j, J̇ v = |v_i − v_j|² (j = None: a fixed pivot at the origin)."""
    n = len(masses)
    J = np.zeros((len(rods), 3 * n))
    rhs = np.zeros(len(rods))
    for k, (i, j) in enumerate(rods):
        d = x[i] - (x[j] if j is not None else 0.0)
        w = v[i] - (v[j] if j is not None else 0.0)
        J[k, 3 * i:3 * i + 3] = d
        if j is not None:
            J[k, 3 * j:3 * j + 3] = -d
        rhs[k] = -w @ w
    M = np.repeat(masses, 3)
    F = np.tile(G, n) * M
    K = np.block([[np.diag(M), -J.T], [J, np.zeros((len(rods), len(rods)))]])
    return np.linalg.solve(K, np.concatenate([F, rhs]))[:3 * n].reshape(n, 3)


@pytest.mark.parametrize("method", ["ggl", "idas"])
def test_a_nanosecond_of_the_double_pendulum_scene(method):
    """scenarios/double_pendulum.toml (released at rest) for 1 ns: v(t) = a0 t with a0 from an
    independent KKT solve, to 1e-6; the positions move by a0 t²/2 ~ 5e-18 m, below round-off."""
    system = C.load_scene(SCENARIOS / "double_pendulum.toml").system
    tr = C.simulate(system, 1e-9, method=method, rtol=1e-10, atol=1e-10)
    assert tr.success and tr.t[-1] == 1e-9
    # (the start as the run made it consistent: the scene's positions have 10 digits)
    x0, v0 = tr.x[0], tr.v[0]
    a0 = kkt_accelerations(np.asarray(system.masses, float), x0, v0, [(0, None), (1, 0)])
    assert np.abs(a0).max() > 1.0
    assert np.abs(tr.v[-1] - v0 - a0 * 1e-9).max() < 1e-6 * np.abs(a0).max() * 1e-9
    assert np.abs(tr.x[-1] - x0 - v0 * 1e-9).max() < 1e-15


def test_bench_measures_ggl_and_idas_on_a_nanosecond(tmp_path):
    """`constrained bench` at t_end = 1 ns: ggl's rows were `failed: IDAS stopped after t = 0 s`."""
    out = tmp_path / "b"
    code = main(["bench", str(SCENARIOS / "simple_pendulum.toml"), "--set", "simulate.t_end=1e-9",
                 "--methods", "idas,ggl", "--tolerances", "1e-6,1e-10", "--out", str(out),
                 "--repeats", "1", "--quiet"])
    assert code == 0
    rows = list(csv.DictReader((out / "bench.csv").open()))
    assert [(r["method"], r["status"]) for r in rows] == [
        ("idas", "ok"), ("idas", "ok"), ("ggl", "ok"), ("ggl", "ok")]
    # in 1 ns the bob moves g sin(th0) t²/2 ~ 1e-18 m: every error is at that scale or below
    assert all(float(r["error"]) < 1e-17 for r in rows)
