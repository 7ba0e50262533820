"""The peers of benchmarks/peers.py simulate the same physics as constrained (small cases).

Physics agreement only; the timings live in benchmarks/peers.py and docs/performance/peers/.
The NumPy baseline is always checked; the SymPy, PyDy, Exudyn and MuJoCo peers only when
installed (the bench extra), otherwise these tests are skipped.
"""

from __future__ import annotations

import importlib.util
import sys

import numpy as np
import pytest
from conftest import ROOT

_spec = importlib.util.spec_from_file_location("peers_benchmark", ROOT / "benchmarks" / "peers.py")
peers = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = peers  # dataclasses look their module up while the class is built
_spec.loader.exec_module(peers)

TOL = 1e-7  # end-position agreement [m]; the runs below are at rtol 1e-10 or comparable


@pytest.fixture(scope="module", params=["chain3", "double"])
def case(request):
    """(problem, constrained's end positions (n, 2) at rtol 1e-11)."""
    problem = peers.chain_problem(3) if request.param == "chain3" else peers.double_problem(t_end=0.5)
    system = problem.system()
    _, x, _ = peers.constrained_run(system, problem.t_end, "projection", 1e-11)
    return problem, x[:, :2]


def _check(peer, problem, ref, value):
    _, xy, _ = peer.run(peer.build(problem), problem, value)
    assert np.asarray(xy).shape == ref.shape
    assert np.max(np.abs(np.asarray(xy) - ref)) < TOL


def test_double_problem_starts_where_the_scene_does():
    problem = peers.double_problem(t_end=0.5)
    assert problem.n == 2 and problem.omega0 == (0.0, 0.0)
    assert np.allclose(problem.theta0, (2.0, 2.5), atol=1e-9)  # the scene's positions have 10 decimals
    x = problem.system().positions.reshape(-1, 3)[:, :2]
    assert np.max(np.abs(peers.angles_to_xy(problem.theta0) - x)) < 1e-9


def test_numpy_baseline(case):
    problem, ref = case
    _check(peers.NumpyPeer(), problem, ref, 1e-10)


def test_numpy_chain_function_matches_constrained():
    wall, pos = peers.numpy_chain(3, 1e-10)
    _, x, _ = peers.constrained_run(peers.chain(3), peers.T_END, "projection", 1e-11)
    assert wall > 0 and np.max(np.abs(pos.reshape(-1, 3) - x)) < TOL


def test_sympy_lagrange(case):
    pytest.importorskip("sympy")
    problem, ref = case
    _check(peers.SympyPeer(), problem, ref, 1e-10)


def test_pydy_kane_lambdify(case):
    pytest.importorskip("pydy")
    problem, ref = case
    _check(peers.PydyPeer("lambdify"), problem, ref, 1e-10)


def test_exudyn_kinematic_tree(case):
    pytest.importorskip("exudyn")
    problem, ref = case
    _check(peers.ExudynTreePeer("DOPRI5"), problem, ref, 1e-10)


def test_exudyn_points_and_distances(case):
    pytest.importorskip("exudyn")
    problem, ref = case
    _check(peers.ExudynPointsPeer(sparse=True), problem, ref, 2.5e-5)  # second order: ~1e-8 here


def test_mujoco_hinge_chain(case):
    pytest.importorskip("mujoco")
    problem, ref = case
    _check(peers.MujocoPeer(), problem, ref, 1e-3)  # RK4
