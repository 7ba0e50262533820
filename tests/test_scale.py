"""Issue 9: the fast paths at scale are the same numbers as the dense NumPy KKT path.

Correctness only; timings live in benchmarks/scaling.py, never in tests.
"""

import casadi as ca
import numpy as np
import pytest

import constrained as C
from constrained.codegen.fast_call import FastCall
from constrained.manifold.dense import schur_solve
from constrained.manifold.manifold import (
    Manifold,
    ProjectionStatus,
    acceleration_function,
    symbolic_acceleration,
)


def chain(n: int, bend: float = 0.5) -> C.System:
    s = C.System(name=f"{n}-link chain")
    for i in range(n):
        s.add_particle(f"p{i}", 1.0, [(i + 1) * np.sin(bend), -(i + 1) * np.cos(bend), 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=1.0))
    for i in range(1, n):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=1.0))
    s.add(C.Plane([f"p{i}" for i in range(n)], [0, 0, 1]), C.Gravity([0, -9.81, 0]))
    return s


@pytest.fixture(scope="module")
def small():
    system = chain(6)
    model = C.assemble(system)
    rng = np.random.default_rng(9)
    x = system.positions.ravel() + 1e-3 * rng.standard_normal(3 * 6)
    v = rng.standard_normal(3 * 6)
    return model, x, v


def test_sparse_kkt_matches_dense_schur(small):
    model, x, v = small
    a, lam = Manifold(model).accelerations(x, v, 0.3)
    F, J, gamma = (np.asarray(o, float) for o in model.dynamics(x, v, 0.3))
    F, gamma = F.ravel(), gamma.ravel()
    lam_dense = schur_solve(J, model.inverse_masses, -gamma - J @ (model.inverse_masses * F))
    a_dense = model.inverse_masses * (F + J.T @ lam_dense)
    assert np.max(np.abs(lam - lam_dense)) <= 1e-12 * max(1.0, np.max(np.abs(lam_dense)))
    assert np.max(np.abs(a - a_dense)) <= 1e-12 * max(1.0, np.max(np.abs(a_dense)))
    assert np.max(np.abs(J @ a + gamma)) < 1e-11


def test_projection_steps_match_dense(small):
    model, x, v = small
    f, J = (np.asarray(o, float) for o in model.jacobian(x, 0.0))
    f = f.ravel()
    manifold = Manifold(model)
    one_step = manifold.project_positions(x, 0.0, tol=0.0, max_iter=1)
    dx = x - one_step.x
    dx_dense = model.inverse_masses * (J.T @ schur_solve(J, model.inverse_masses, f))
    assert one_step.iterations == 1 and one_step.status is ProjectionStatus.MAX_ITERATIONS
    assert np.max(np.abs(dx - dx_dense)) <= 1e-12 * max(1.0, np.max(np.abs(dx_dense)))
    v_new = manifold.project_velocities(x, v, 0.0)
    v_dense = v - model.inverse_masses * (J.T @ schur_solve(J, model.inverse_masses, J @ v))
    assert np.max(np.abs(v_new - v_dense)) <= 1e-12 * max(1.0, np.max(np.abs(v)))


def test_buffer_calls_identical_to_ordinary_calls(small):
    """The FunctionBuffer route returns exactly what a plain CasADi call returns, and its
    results are copies (a later call does not overwrite them)."""
    model, x, v = small
    function = acceleration_function(model)
    inputs = function.mx_in()
    fast = FastCall(ca.Function("dense", inputs, [ca.densify(o) for o in function.call(inputs)]))
    a1, lam1 = fast(x, v, 0.3)
    a2, lam2 = (np.asarray(o, float).ravel() for o in function(x, v, 0.3))
    assert np.array_equal(a1, a2) and np.array_equal(lam1, lam2)
    kept = a1.copy()
    fast(x + 0.01, v, 0.3)
    assert np.array_equal(a1, kept)


def test_released_buffers_are_made_again_with_the_same_results(small, monkeypatch):
    """``release_large`` frees the buffers of the FastCalls with a work vector of LARGE_WORK
    doubles or more (here the acceleration's, the threshold lowered below it), not the others'
    (a Function with no work vector); a released FastCall's next call makes them again and gives
    the same bits as before."""
    from constrained.codegen import fast_call

    model, x, v = small
    function = acceleration_function(model)
    inputs = function.mx_in()
    dense = ca.Function("dense", inputs, [ca.densify(o) for o in function.call(inputs)])
    monkeypatch.setattr(fast_call, "LARGE_WORK", dense.sz_w())
    large = FastCall(dense)
    small_call = FastCall(ca.Function("twice", [inputs[0]], [2 * inputs[0]]))
    before, doubled = large(x, v, 0.3), small_call(x)
    fast_call.release_large()
    assert large._local.state is None and small_call._local.state is not None
    after = large(x, v, 0.3)
    assert all(np.array_equal(b, a) for b, a in zip(before, after, strict=True))
    assert np.array_equal(small_call(x)[0], doubled[0]) and np.array_equal(doubled[0], 2 * x)


def test_buffer_calls_without_constraints():
    s = C.System()
    s.add_particle("p", 2.0, [0, 0, 0])
    s.add(C.Gravity([0, 0, -9.81]))
    model = C.assemble(s)
    a, lam = Manifold(model).accelerations(np.zeros(3), np.zeros(3), 0.0)
    assert np.allclose(a, [0, 0, -9.81]) and lam.size == 0


def test_hanging_chain_200_links_conserves_energy():
    """N = 200 released from a bent start: energy conserved, constraints at round-off."""
    system = chain(200)
    tr = C.simulate(system, 0.1, rtol=1e-8, atol=1e-10, t_eval=np.linspace(0, 0.1, 6), compiled=False,
                    outputs={"energy", "constraint_residual", "velocity_residual"})
    scale = np.max(np.abs(tr.energy))
    assert np.max(np.abs(tr.energy - tr.energy[0])) <= 1e-7 * scale
    assert np.max(tr.constraint_residual) <= 1e-10
    assert np.max(tr.velocity_residual) <= 1e-10
    assert np.max(np.abs(tr.x[-1] - tr.x[0])) > 1e-3  # it did move


def test_sparse_and_cholesky_full_rank_tests_agree_with_the_rank_revealing_qr(monkeypatch):
    import itertools

    from constrained.manifold.algebra import DENSE, SPARSE
    from constrained.manifold.constraint_report import jacobian_rank

    chain = C.System()
    for i in range(30):
        chain.add_particle(f"p{i}", 1.0 + i, [np.sin(0.5) * (i + 1), -np.cos(0.5) * (i + 1), 0.0])
    chain.add(C.Distance("p0", point=[0, 0, 0], length=1.0))
    for i in range(1, 30):
        chain.add(C.Distance(f"p{i - 1}", f"p{i}", length=1.0))
    cube = C.System()
    pts = np.array(list(itertools.product([-0.5, 0.5], repeat=3)))
    for i, p in enumerate(pts):
        cube.add_particle(f"c{i}", 1.0, p)
    for i, j in itertools.combinations(range(8), 2):
        cube.add(C.Distance(f"c{i}", f"c{j}", length=float(np.linalg.norm(pts[i] - pts[j]))))
    for system, full in ((chain, True), (cube, False)):
        model = C.assemble(system)
        J = model.jacobian(system.positions.ravel(), 0.0)[1]
        for algebra in (SPARSE, DENSE):  # the sparse LU, then the dense Cholesky
            assert bool(algebra.full_row_rank(J, model.inverse_masses)) is full
            assert (algebra.independent_rows(J, model.inverse_masses).size == model.n_constraints) is full
        assert (jacobian_rank(np.asarray(J))[0] == model.n_constraints) is full


def test_symbolic_acceleration_matches_the_sparse_solve(small):
    """dopri's SX-expanded step (small models) writes the KKT solve out symbolically; it must
    give the sparse fast path's accelerations and multipliers."""
    model, x, v = small
    a, lam = Manifold(model).accelerations(x, v, 0.3)
    a_sx, lam_sx = (np.asarray(o, float).ravel() for o in symbolic_acceleration(model)(x, v, 0.3))
    assert np.max(np.abs(a_sx - a)) <= 1e-12 * max(1.0, np.max(np.abs(a)))
    assert np.max(np.abs(lam_sx - lam)) <= 1e-12 * max(1.0, np.max(np.abs(lam)))
